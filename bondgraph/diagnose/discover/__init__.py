"""Effects beyond the library: reconstruct what is missing at a port and
discover its law (issue 29).

* :mod:`.reconstruct`: the missing effort (flow) at a 1-junction (0-junction)
  as an integrated random walk, UKF + unscented RTS smoother
  (:func:`reconstruct`, :class:`ReconstructOptions`, :class:`Reconstruction`);
  the offset missing at a sensor's output the same way
  (:func:`reconstruct_sensor`, :func:`augment_sensor`).
* :mod:`.law`: a sparse regression of the reconstructed signal on a
  dictionary of the port's variables, with at most one memory term, a
  first-order low-pass of one of them (:func:`discover_law`,
  :class:`DiscoverOptions`, :class:`DiscoveredLaw`).
* :mod:`.passivity`: a discovered law's R part dissipates, its storage part
  keeps the stored energy >= 0; offending terms dropped and named
  (:func:`make_passive`, :class:`PassivityReport`).
* :mod:`.effect`: the discovered law as a loop effect at its 1-junction
  (:class:`DiscoveredEffect`) or at its sensor (:class:`DiscoveredSensorEffect`), :func:`discover_effect` (the three above at
  one port), :func:`loop_with_discovery` (the loop, then discovery where no
  physical effect was accepted, then the loop again with it).
"""

from bondgraph.diagnose.discover.effect import (
    DiscoveredEffect,
    DiscoveredSensorEffect,
    Discovery,
    discover_effect,
    loop_with_discovery,
)
from bondgraph.diagnose.discover.law import DiscoveredLaw, DiscoverOptions, Term, discover_law
from bondgraph.diagnose.discover.passivity import PassivityReport, make_passive
from bondgraph.diagnose.discover.reconstruct import (
    PortAugmentation,
    Reconstruction,
    ReconstructOptions,
    augment_port,
    augment_sensor,
    reconstruct,
    reconstruct_sensor,
)

__all__ = ["DiscoveredEffect", "DiscoveredSensorEffect", "Discovery", "discover_effect",
           "loop_with_discovery", "DiscoverOptions", "DiscoveredLaw", "PassivityReport",
           "PortAugmentation", "ReconstructOptions", "Reconstruction", "Term", "augment_port",
           "augment_sensor", "discover_law", "make_passive", "reconstruct", "reconstruct_sensor"]
