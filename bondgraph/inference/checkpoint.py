"""Fingerprints of an estimation problem, stored in optimizer checkpoints.

``--resume`` must continue the *same* problem. A checkpoint therefore holds
a fingerprint: named components, each the text of a small setting or the
SHA-256 of an array (:func:`digest`),

* from the problem (:func:`problem_fingerprint`): the record's arrays in the
  model's units (t, u, y), the model (its generated source), the list of
  estimated parameters, the values of the others (fixed and defaults), the
  UKF prior (x0, P0), the extra noise (Q, R) and the UKF options;
* from the optimizer (:func:`bondgraph.inference.optimize.pso`, ``de``): the
  swarm size, seed, coefficients, search box and start point.

On resume, :func:`check` compares them and refuses on any difference,
naming each component that differs. The iteration budget is not part of it:
a finished run may be continued with more iterations.
"""

from __future__ import annotations

import hashlib
import json
import re
from typing import Mapping

import numpy as np

from bondgraph.errors import CheckpointError

#: longest component value shown in a message (hashes are never shown)
_SHOWN_MAX = 60
_HASH = re.compile(r"^[0-9a-f]{16}$")


def digest(*arrays) -> str:
    """SHA-256 (16 hex digits) of arrays: dtype, shape and bytes of each
    (``None`` counts as itself)."""
    h = hashlib.sha256()
    for a in arrays:
        if a is None:
            h.update(b"none;")
            continue
        arr = np.ascontiguousarray(np.asarray(a, dtype=float))
        h.update(f"{arr.dtype.str}{arr.shape};".encode())
        h.update(arr.tobytes())
    return h.hexdigest()[:16]


def model_digest(model) -> str:
    """The model's name and the SHA-256 of its generated source (equations,
    parameters, defaults and bounds)."""
    mod = getattr(model, "module", None)
    text = getattr(mod, "__source_text__", None)
    if text is None and getattr(mod, "__file__", None):
        with open(mod.__file__, encoding="utf-8") as fh:
            text = fh.read()
    if text is None:                     # not a generated module: its declared content
        text = json.dumps([model.name, model.states, model.inputs, model.params, model.outputs,
                           np.asarray(model.theta0).tolist()])
    return f"{model.name} {hashlib.sha256(text.encode()).hexdigest()[:16]}"


def problem_fingerprint(crit) -> dict[str, str]:
    """The problem components of an estimation criterion
    (:class:`bondgraph.inference.estimate.Criterion`; a ``JointCriterion``'s
    are its records', each key prefixed with the record's position)."""
    members = getattr(crit, "members", None)
    if members is not None:
        return {f"record {i + 1}: {k}": v for i, m in enumerate(members)
                for k, v in problem_fingerprint(m).items()}
    fp = {
        "data (t, u, y arrays)": digest(crit.t, crit.u, crit.y),
        "model": model_digest(crit.model),
        "parameter list": ", ".join(crit.params),
        "values of the other parameters": digest(crit.base),
        "prior x0, P0": digest(crit.x0, crit.P0),
        "noise Q, R": digest(crit.Q, crit.R),
        "UKF options": json.dumps(crit.options.to_dict(), sort_keys=True),
    }
    est = getattr(crit, "est", None)
    if est is not None:      # an EstimandCriterion: the held noise stds too
        fp["measurement-noise stds held"] = digest(est.sigma)
    return fp


def encode(fingerprint: Mapping[str, str]) -> np.ndarray:
    """The fingerprint as a 0-d string array for ``np.savez``."""
    return np.array(json.dumps(dict(fingerprint), sort_keys=True))


def check(path, stored, current: Mapping[str, str]) -> None:
    """Refuse a checkpoint whose fingerprint differs from ``current``.

    Parameters
    ----------
    path : path
        The checkpoint (for messages).
    stored : str or None
        The checkpoint's ``fingerprint`` entry (None: a checkpoint without one).
    current : dict
        The fingerprint of the problem to resume.

    Raises
    ------
    CheckpointError
        Naming every component that differs (with both values where short).
    """
    if stored is None:
        raise CheckpointError(f"checkpoint {path} carries no fingerprint of its problem "
                              f"(written by an older version); not resuming",
                              hint="start afresh without --resume")
    old = json.loads(str(stored))
    differs = sorted(k for k in set(old) | set(current) if old.get(k) != current.get(k))
    if not differs:
        return
    parts = []
    for k in differs:
        a, b = old.get(k), current.get(k)
        shown = all(v is not None and len(v) <= _SHOWN_MAX and not _HASH.match(v)
                    for v in (a, b))
        parts.append(f"{k} (checkpoint: {a}, now: {b})" if shown else k)
    raise CheckpointError(
        f"checkpoint {path} was written for another problem: {'; '.join(parts)} "
        f"differ{'s' if len(differs) == 1 else ''}; not resuming", differs=differs,
        hint="resume with the record, model, parameters and options of the interrupted run, "
             "or start afresh without --resume")
