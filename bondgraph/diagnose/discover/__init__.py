"""Effects beyond the library: reconstruct what is missing at a port and
discover its law (issue 29).

* :mod:`.reconstruct`: the missing effort (flow) at a 1-junction (0-junction)
  as an integrated random walk, UKF + unscented RTS smoother
  (:func:`reconstruct`, :class:`ReconstructOptions`, :class:`Reconstruction`).
* :mod:`.law`: a sparse regression of the reconstructed signal on a
  dictionary of the port's variables (:func:`discover_law`,
  :class:`DiscoverOptions`, :class:`DiscoveredLaw`).
* :mod:`.passivity`: a discovered law's R part dissipates, its storage part
  keeps the stored energy >= 0; offending terms dropped and named
  (:func:`make_passive`, :class:`PassivityReport`).
* :mod:`.effect`: the discovered law as a loop effect at its 1-junction
  (:class:`DiscoveredEffect`), :func:`discover_effect` (the three above at
  one port), :func:`loop_with_discovery` (the loop, then discovery where no
  physical effect was accepted, then the loop again with it).
"""

from bondgraph.diagnose.discover.effect import (
    DiscoveredEffect,
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
    reconstruct,
)

__all__ = ["DiscoveredEffect", "Discovery", "discover_effect", "loop_with_discovery",
           "DiscoverOptions", "DiscoveredLaw", "PassivityReport", "PortAugmentation", "ReconstructOptions",
           "Reconstruction", "Term", "augment_port", "discover_law", "make_passive", "reconstruct"]
