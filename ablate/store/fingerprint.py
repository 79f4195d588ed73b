"""A job's fingerprint as the store keeps it: numbers per component, compared with a relative tolerance.

Computed by :func:`ablate.jobs.fingerprint.compute` at a job's start; stored as the run's ``fingerprint`` tag
(compact JSON); compared by the tables (:mod:`ablate.tables.provenance`) with :func:`differs`.
"""

from __future__ import annotations

import json
import math
import re

import numpy as np

#: The components in the order a difference is looked for: the first that differs is named.
COMPONENTS = ("data", "model", "loss", "schedule", "metric", "corruptions")
#: Relative tolerance of a comparison on the kernels the fingerprint was recorded with.
RTOL, ATOL = 1e-4, 1e-8
#: Across instruction sets' kernels (AVX-512, AVX2, SSE: ``ATEN_CPU_CAPABILITY``, ``ONEDNN_MAX_CPU_ISA``), measured
#: over every row and expert of every table (``scripts/fingerprints.py`` under each setting, AMD EPYC family 25 model
#: 17): data and schedule agree exactly, the model's outputs within 2.9e-4 (relative), while the loss after two
#: optimiser steps moves up to 9 % (SMoE's backbone row, SSE against AVX-512) and the test metrics up to 0.7 %
#: (DGFN): rounding that the optimiser and a detector's discrete choices amplify. The same AVX-512 kernels of ATen on
#: another CPU round otherwise too (oneDNN and the BLAS choose their kernels and blocking by the CPU, not by the ISA
#: alone): every published row recomputed on an Intel Xeon family 6 model 106 against its records from the AMD EPYC
#: model 17 gave the model's outputs within 1.5e-4, the loss within 8.5e-4 and the metrics within 4.1e-3 (BiFNet's
#: image row). Across kernels (:func:`kernel_family`: another ISA's, or another CPU's) only the components that stay
#: put are compared, at a tolerance above their measured spread; the loss and the metric are compared like with like
#: only.
ACROSS = {"data": RTOL, "model": 2e-3, "schedule": RTOL}
TAG = "fingerprint"


def differs(
    recorded: dict[str, list[float]], today: dict[str, list[float]], across_kernels: bool = False
) -> str | None:
    """The first component (:data:`COMPONENTS`) whose numbers differ beyond ``RTOL``, or None; ``across_kernels``:
    the two were computed on other instruction sets' kernels, and only :data:`ACROSS` is compared, each at its own
    tolerance. A component one side has and the other lacks (a record made before it was fingerprinted), or with
    another count of numbers, differs on any kernels."""
    for name in COMPONENTS:
        a, b = recorded.get(name), today.get(name)
        if a is None or b is None or len(a) != len(b):  # another shape is not rounding, on any kernels
            if a != b:
                return name
            continue
        if across_kernels and name not in ACROSS:
            continue
        rtol = ACROSS[name] if across_kernels else RTOL
        if not np.allclose(np.asarray(a, float), np.asarray(b, float), rtol=rtol, atol=ATOL, equal_nan=True):
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


def kernel_family(kernels: str = "", isa: str = "", cpu: str = "") -> str:
    """The kernels a run's numbers came from: the instruction set's (its recorded ``cpu_kernels``,
    :func:`ablate.hardware.kernels`, ``AVX512``, ``AVX2; oneDNN AVX2``, or, for records made before it, the best its
    CPU's ISA flags ``cpu_isa`` give torch by default) on its CPU (``cpu``, :func:`ablate.hardware.cpu`'s model:
    the vendor, family and model, ``AVX512 on AMD family 25 model 17``), where that is known; "" where the
    instruction set is not."""
    if kernels and kernels not in ("?", "not recorded"):
        family = kernels.upper()
    else:
        flags = set(isa.split())
        family = "AVX512" if "avx512f" in flags else "AVX2" if "avx2" in flags else ""
    return f"{family} on {chip}" if family and (chip := cpu_chip(cpu)) else family


def cpu_chip(cpu: str) -> str:
    """The vendor, family and model of a CPU's recorded name (``AMD EPYC (family 25, model 17)`` -> ``AMD family 25
    model 17``); "" where the name does not give the family and model (a record made before they were named)."""
    found = re.search(r"\(family (\w+), model (\w+)\)\s*$", cpu)
    if not found:
        return ""
    words = cpu.split()
    vendor = "AMD" if "AMD" in words else "Intel" if any(w.startswith("Intel") for w in words) else words[0]
    return f"{vendor} family {found.group(1)} model {found.group(2)}"
