"""A job's fingerprint as the store keeps it: numbers per component, compared with a relative tolerance.

Computed by :func:`ablate.jobs.fingerprint.compute` at a job's start; stored as the run's ``fingerprint`` tag
(compact JSON); compared by the tables (:mod:`ablate.tables.provenance`) with :func:`differs`.
"""

from __future__ import annotations

import json
import math

import numpy as np

#: The components in the order a difference is looked for: the first that differs is named.
COMPONENTS = ("data", "model", "loss", "schedule", "metric")
#: Relative tolerance of a comparison: machines with other kernels (AVX2, AVX-512) agree within it.
RTOL, ATOL = 1e-4, 1e-8
TAG = "fingerprint"


def differs(recorded: dict[str, list[float]], today: dict[str, list[float]]) -> str | None:
    """The first component (:data:`COMPONENTS`) whose numbers differ beyond ``RTOL``, or None."""
    for name in COMPONENTS:
        a, b = recorded.get(name), today.get(name)
        if a is None or b is None or len(a) != len(b):
            if a != b:
                return name
            continue
        if not np.allclose(np.asarray(a, float), np.asarray(b, float), rtol=RTOL, atol=ATOL, equal_nan=True):
            return name
    return None


def encode(fingerprint: dict[str, list[float]]) -> str:
    """The fingerprint as the run's ``fingerprint`` tag: compact JSON, 10 significant digits."""
    return json.dumps(
        {k: [float(f"{v:.10g}") if math.isfinite(v) else str(v) for v in values] for k, values in fingerprint.items()},
        separators=(",", ":"),
    )


def decode(text: str) -> dict[str, list[float]]:
    """The numbers of a ``fingerprint`` tag."""
    return {k: [float(v) for v in values] for k, values in json.loads(text).items()}
