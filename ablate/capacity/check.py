"""The paper path, exercised on the CPU: every row of every table at ``scale=paper`` builds its data, model and task and
runs one training step and one evaluation step at batch 1, with its memory and GPU time estimated from them.

``python -m ablate.check_paper [experiment=a,b] [row=x,y] [budget_min=40] [force=true] [reuse=true]``
(:mod:`ablate.check_paper`; :func:`main`). The pieces, one job each:

- :mod:`ablate.capacity.rows`: the rows, their job configs, what each trains and its recipe (batch, steps, seeds);
- :mod:`ablate.capacity.measure`: one row's training and test step, and the figures measured on them;
- :mod:`ablate.capacity.estimates`: GPU memory and GPU-hours from those figures, for the GPUs named there;
- :mod:`ablate.capacity.report`: ``results/paper_scale.md``;
- this module: each measurement in a process of its own (:func:`run_isolated`: its peak RSS, ``resource.getrusage``,
  is the row's, and a crash is the row's error), under a time budget, the CPU it ran on recorded (:func:`cpu_name`,
  with the CPU's family and model numbers); the store of figures; the command.

``reuse=true`` times no step: it counts the frozen MACs of stored measurements made before they were counted
(:func:`recount`: the model built, one training forward pass counted) and rewrites the markdown from the stored
figures and today's configs (recipes, steps, seeds), saying which CPU gave which figures.

The measurements are kept per measured configuration in ``results/paper_scale.json`` (rows of several tables with
one model, task and data share one); ``results/paper_scale.md`` lists every row of every table from them, a row
not measured here saying why. Both are written through :mod:`ablate.tables.published`.
"""

from __future__ import annotations

import concurrent.futures
import json
import logging
import multiprocessing
import platform
import resource
import subprocess
import tempfile
import time
import traceback
import warnings
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

from ablate import cli, hardware
from ablate.capacity.measure import count_macs, measure, sample_config
from ablate.capacity.report import failed, line, report
from ablate.capacity.rows import describe, experiments, measured_config, order, plan, recipe
from ablate.tables import published


def _child(spec: tuple[str, str, str | None], data_dir: str, overrides: list[str]) -> dict[str, Any]:
    """One measurement in a fresh process (:func:`run_isolated`): its figures and its peak RSS."""
    logging.disable(logging.WARNING)
    warnings.filterwarnings("ignore")
    cfg = measured_config(*spec, overrides=overrides)
    out = measure(cfg, sample_config(cfg, data_dir), recipe(cfg)["steps"])
    out["peak_rss"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    return out


def _count_child(spec: tuple[str, str, str | None], data_dir: str, overrides: list[str]) -> dict[str, Any]:
    """One MAC count in a fresh process (:func:`count_isolated`)."""
    logging.disable(logging.WARNING)
    warnings.filterwarnings("ignore")
    cfg = measured_config(*spec, overrides=overrides)
    return count_macs(cfg, sample_config(cfg, data_dir))


def _isolated(fn: Any, spec: tuple[str, str, str | None], data_dir: str, overrides: Iterable[str]) -> dict[str, Any]:
    context = multiprocessing.get_context("spawn")
    with concurrent.futures.ProcessPoolExecutor(1, mp_context=context) as pool:
        return pool.submit(fn, spec, data_dir, list(overrides)).result()


def run_isolated(spec: tuple[str, str, str | None], data_dir: str, overrides: Iterable[str] = ()) -> dict[str, Any]:
    """:func:`_child` in a fresh (spawned) process: its peak RSS is the row's, and a crash is the row's error."""
    return _isolated(_child, spec, data_dir, overrides)


def count_isolated(spec: tuple[str, str, str | None], data_dir: str, overrides: Iterable[str] = ()) -> dict[str, Any]:
    """:func:`count_macs` of a measurement's config in a fresh (spawned) process."""
    return _isolated(_count_child, spec, data_dir, overrides)


def cpu_name() -> str:
    """This machine's CPU as ``lscpu`` names it, with its family and model numbers (one model name covers CPUs of
    several generations), its cores and ISA flags."""
    try:
        text = subprocess.run(["lscpu"], capture_output=True, text=True, check=True).stdout
        fields = {k.strip(): v.strip() for k, v in (line.split(":", 1) for line in text.splitlines() if ":" in line)}
        name = fields.get("Model name", "") or hardware.cpu().model
        if fields.get("CPU family") and fields.get("Model"):
            name += f", family {fields['CPU family']} model {fields['Model']}"
    except (OSError, subprocess.CalledProcessError):
        name = hardware.cpu().model or platform.processor()
    return f"{name} ({hardware.cores()} cores, {hardware.cpu().isa})"


def check(
    entries: list[dict[str, Any]],
    measured: dict[str, Any],
    budget_s: float | None = None,
    overrides: Iterable[str] = (),
    save: Callable[[dict[str, Any]], None] = lambda measured: None,
    echo: Callable[[str], None] = print,
) -> dict[str, Any]:
    """Measure what ``entries`` train (:func:`order`) and is not in ``measured`` (or failed there), each in a
    process of its own, until ``budget_s`` seconds have passed; ``measured`` (key -> figures, or {"error": ...})
    is updated, and handed to ``save`` after each measurement."""
    start = time.perf_counter()
    cpu = cpu_name()
    with tempfile.TemporaryDirectory(prefix="ablate-paper-") as data_dir:
        for key, spec in order(entries):
            if key in measured and "error" not in measured[key]:
                continue
            name = f"{spec[0]}/{spec[1]}" + (f" (expert {spec[2]})" if spec[2] else "")
            if budget_s is not None and time.perf_counter() - start > budget_s:
                echo(f"{name:44s} not run: the time budget of {budget_s / 60:.0f} min is spent")
                continue
            echo(f"{name:44s} running ...")
            try:
                figures = run_isolated(tuple(spec), data_dir, overrides)
            except Exception as err:  # anything the row's own process raised (its model, its data) is its result
                message = f"{type(err).__name__}: {err}".strip()
                measured[key] = {"error": message, "where": name, "traceback": traceback.format_exc()[-4000:]}
                echo(f"{name:44s} FAILED: {message}")
            else:
                measured[key] = {**figures, "where": name, "cpu": cpu}
                echo(line(name, figures, next(e for e in entries if key in (e["key"], *e["experts"].values()))))
            save(measured)
    return measured


def recount(
    entries: list[dict[str, Any]],
    measured: dict[str, Any],
    budget_s: float | None = None,
    overrides: Iterable[str] = (),
    save: Callable[[dict[str, Any]], None] = lambda measured: None,
    echo: Callable[[str], None] = print,
) -> dict[str, Any]:
    """Count the frozen MACs (:func:`count_macs`) of every stored measurement of a row on frozen experts that has
    no count of them (one made before they were counted), each in a process of its own, until ``budget_s`` seconds
    have passed; the measurement's other figures are kept, the count's CPU recorded as ``count_cpu``. A count whose
    total MACs differ from the stored ones (the same forward pass, so they should not) keeps both, and says so."""
    start, cpu, done = time.perf_counter(), cpu_name(), set()
    with tempfile.TemporaryDirectory(prefix="ablate-paper-") as data_dir:
        for e in entries:
            m = measured.get(e["key"])
            if not e["frozen"] or m is None or "error" in m or m.get("macs_frozen") is not None or e["key"] in done:
                continue
            done.add(e["key"])
            name = m["where"]
            if budget_s is not None and time.perf_counter() - start > budget_s:
                echo(f"{name:44s} not counted: the time budget of {budget_s / 60:.0f} min is spent")
                continue
            echo(f"{name:44s} counting MACs ...")
            try:
                counted = count_isolated(tuple(e["spec"]), data_dir, overrides)
            except Exception as err:  # anything the row's own process raised (its model, its data) is its result
                m["count_error"] = f"{type(err).__name__}: {err}".strip()
                echo(f"{name:44s} FAILED: {m['count_error']}")
            else:
                m.pop("count_error", None)
                m.update(macs_frozen=counted["macs_frozen"], feature_bytes=counted["feature_bytes"], count_cpu=cpu)
                if counted["macs"] != m["macs"]:
                    m["macs_counted"] = counted["macs"]
                    echo(f"{name:44s} warning: {counted['macs']:,} MACs counted, {m['macs']:,} stored")
                echo(
                    f"{name:44s} {m['macs'] / 1e9:8.1f} GMACs, {counted['macs_frozen'] / 1e9:8.1f} of them frozen; "
                    f"frozen features {counted['feature_bytes'] / 2**20:.1f} MiB a frame"
                )
            save(measured)
    return measured


def _read(path: Path, empty: Any) -> Any:
    """The JSON in ``path`` (``empty`` where there is no file); ValueError naming the file where it is not JSON."""
    if not path.is_file():
        return empty
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path} is not valid JSON ({exc}); fix or remove it") from None


def main(argv: list[str] | None = None) -> int:
    """``python -m ablate.check_paper [experiment=a,b] [row=x,y] [budget_min=N] [force=true] [reuse=true]
    [key=value ...]``: measure the chosen rows (all by default) not measured yet (``force=true``: again), keep the
    figures in ``results/paper_scale.json``, write ``results/paper_scale.md`` for every row of every table; exit 1
    when a row fails. ``reuse=true``: time no step; count the frozen MACs of the stored measurements that lack them
    (:func:`recount`; ``force=true``: of all of the chosen rows) and rewrite the markdown from the stored figures
    and today's configs. The arguments are read by :func:`ablate.cli.check_paper`: ``--help``, a bad option and an
    unknown experiment end the process there (status 0, 2 and 2)."""
    args = cli.check_paper(__doc__, argv, tables=experiments())
    chosen, overrides = args.experiment, args.overrides
    # the figures files first: a bad one is one line before every table's configs are composed (seconds)
    store, gpu_store = published.path("paper_scale.json"), published.path("paper_scale_gpu.json")  # bench_paper_gpu
    sweeps_store = published.path("paper_scale_sweeps.json")  # bench/gpu_sweeps.py
    try:
        record, gpu, sweeps = _read(store, {}), _read(gpu_store, []), _read(sweeps_store, [])
    except ValueError as exc:
        print(f"error: {exc}")
        return 2
    rows = args.row
    everything = describe(plan(), overrides)
    entries = [e for e in everything if (not chosen or e["table"] in chosen) and (not rows or e["row"] in rows)]
    if not entries:
        print("error: no row of the chosen tables is named " + ", ".join(rows))
        return 2
    keys = {k for e in everything for k in (e["key"], *e["experts"].values())}
    measured = {k: v for k, v in record.get("measured", {}).items() if k in keys}  # those of today's configs
    reuse = args.reuse
    if args.force:
        for e in entries:
            for k in (e["key"], *e["experts"].values()):
                if reuse and k in measured:
                    measured[k].pop("macs_frozen", None)
                elif not reuse:
                    measured.pop(k, None)

    def save(measured: dict) -> None:
        # the measurements of configs no row has today stay stored: nothing measured is lost to a config's change
        kept = {**record.get("measured", {}), **measured}
        text = json.dumps({"written_on": cpu_name(), "measured": kept}, indent=1, sort_keys=True)
        published.write_text(store.name, text + "\n")

    budget = args.budget_min * 60 if args.budget_min is not None else None
    (recount if reuse else check)(entries, measured, budget, overrides, save)
    save(measured)
    figures = {"rows": everything, "measured": measured, "cpu": cpu_name(), "gpu": gpu, "sweeps": sweeps}
    path = published.write_text("paper_scale.md", report(figures) + "\n")
    print(path)
    if bad := failed(entries, measured):
        print(f"error: {len(bad)} row(s) failed: {', '.join(bad)}")
        return 1
    return 0
