"""Time and peak memory of one forward + backward on the CPU, shared by the fusion benchmarks.

Time: median wall-clock seconds over ``repeats`` runs after one warm-up run.
Peak memory: from the CPU allocator events that torch.profiler (profile_memory=True) records during one extra
run, the peak of the bytes allocated in that run and still live (activations, outputs, gradients); what
existed before (inputs, parameters) is not counted.
"""

from __future__ import annotations

import gc
import json
import os
import statistics
import tempfile
import time
from collections.abc import Callable

from torch.profiler import ProfilerActivity, profile


def measure(step: Callable[[], None], repeats: int = 3) -> tuple[float, int]:
    """(median seconds, peak bytes) of ``step``, which runs one forward + backward and frees its results."""
    step()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        step()
        times.append(time.perf_counter() - t0)
    gc.collect()
    with profile(activities=[ProfilerActivity.CPU], profile_memory=True) as prof:
        step()
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "trace.json")
        prof.export_chrome_trace(path)
        with open(path) as f:
            events = json.load(f)["traceEvents"]
    return statistics.median(times), peak_bytes(events)


def peak_bytes(events: list[dict]) -> int:
    """Peak of the bytes allocated within the trace and still live; frees of older blocks are ignored."""
    mem = sorted(
        (e["ts"], e["args"]) for e in events if e.get("name") == "[memory]" and e["args"].get("Device Type") == 0
    )
    live: dict[int, int] = {}
    now = peak = 0
    for _, a in mem:
        if a["Bytes"] > 0:
            live[a["Addr"]] = a["Bytes"]
            now += a["Bytes"]
            peak = max(peak, now)
        elif a["Addr"] in live:
            now -= live.pop(a["Addr"])
    return peak


def table(rows: list[tuple[str, float, int]], reference: str, extra: dict[str, list[str]] | None = None) -> str:
    """A markdown table of (name, seconds, peak bytes) with ratios to the ``reference`` row."""
    ref = {name: (t, m) for name, t, m in rows}[reference]
    extra = extra or {}
    head = ["name", "fwd+bwd ms", f"x {reference}", "peak MiB", f"x {reference}"] + list(extra)
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for i, (name, t, m) in enumerate(rows):
        cells = [
            name,
            f"{t * 1e3:.1f}",
            f"{t / ref[0]:.2f}",
            f"{m / 2**20:.1f}",
            f"{m / ref[1]:.2f}" if ref[1] else "-",
        ]
        lines.append("| " + " | ".join(cells + [v[i] for v in extra.values()]) + " |")
    return "\n".join(lines)
