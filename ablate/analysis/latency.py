"""Latency side by side: every row of a table timed in one process, interleaved, after training.

``python -m ablate.latency experiment=chinet_table2`` (other ``key=value`` overrides apply, e.g.
``comp_time.repeats=50``); a multirun runs it by itself at its end unless ``comp_time.after_sweep=false``.

A latency timed inside each training job measures whatever else the machine did at that moment; rows timed at
different times are not comparable. Here each row's model (its best checkpoint) is loaded into one process and
the rows' forward passes are interleaved: ``comp_time.repeats`` rounds, each timing one forward pass of every row
at batch 1 (the first test frame of the row's own inputs), in an order rotated by one row per round, after
``comp_time.warmup`` untimed rounds, with ``comp_time.threads`` intra-op threads, on ``comp_time.device`` (``auto``:
CUDA where there is one, else the CPU). Load on the machine then slows every row alike, and the median
and interquartile range over rounds show what is left. The load average and the available cores are recorded at
the start and at the end; the table warns when the load exceeded the cores.

Per row, every FINISHED run of the row (all seeds: one architecture, one figure) gets the metrics ``latency_ms``
(median), ``latency_q1_ms``, ``latency_q3_ms``, ``latency_load`` (the larger load average), ``latency_cores``,
``params_m`` and ``macs_g`` (multiply-accumulates of one forward pass: half the FLOPs that
``torch.utils.flop_counter.FlopCounterMode`` counts, i.e. convolutions and matrix products), and the tags
``latency_threads`` and ``latency_device``.
"""

from __future__ import annotations

import logging
import os
import statistics
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import pandas as pd
import torch
from hydra.errors import HydraException
from hydra.utils import instantiate
from mlflow.entities import Run
from omegaconf import DictConfig
from torch.utils.flop_counter import FlopCounterMode

from ablate import cli, hardware
from ablate.config import compose as compose_root
from ablate.config import composition_error
from ablate.jobs import fingerprint
from ablate.jobs.experts import expert_config, load_model
from ablate.jobs.spec import best_checkpoint
from ablate.store import Tracker
from ablate.tables import collect, published, table_spec
from ablate.tables.collect import loaded_runs

log = logging.getLogger(__name__)


def interleaved(
    forwards: dict[str, Callable[[], object]],
    rounds: int,
    warmup: int = 3,
    clock: Callable[[], float] = time.perf_counter,
    sync: Callable[[], None] = lambda: None,
) -> dict[str, list[float]]:
    """Times in ms of each of ``forwards`` over ``rounds`` rounds, round-robin, the order rotated each round so
    that no row always runs first (or right after the same neighbour); ``warmup`` untimed rounds first."""
    names = list(forwards)
    times: dict[str, list[float]] = {n: [] for n in names}
    for r in range(warmup + rounds):
        for name in names[r % len(names) :] + names[: r % len(names)]:
            sync()
            start = clock()
            forwards[name]()
            sync()
            if r >= warmup:
                times[name].append(1000.0 * (clock() - start))
    return times


def quartiles(times: list[float]) -> tuple[float, float, float]:
    """(first quartile, median, third quartile)."""
    if len(times) < 2:
        return times[0], times[0], times[0]
    q1, q2, q3 = statistics.quantiles(times, n=4, method="inclusive")
    return q1, q2, q3


def machine_load() -> tuple[float, int]:
    """The 1-minute load average and the cores this process may use."""
    return os.getloadavg()[0], hardware.cores()


def macs(model: torch.nn.Module, sample: dict) -> int:
    """Multiply-accumulates of one forward pass of ``model`` on ``sample`` (FLOPs / 2 of FlopCounterMode)."""
    with torch.inference_mode(), FlopCounterMode(display=False) as counter:
        model(sample)
    return counter.get_total_flops() // 2


def row_checkpoint(tracker: Tracker, run: Run) -> Path | None:
    """The best checkpoint of a job run, found from its tags (``checkpoints/<table>/<config hash>/``,
    :func:`ablate.jobs.spec.best_checkpoint`), not from a recomputed hash; a run reused from another table's
    (``reused_from``) has its source's; a single-modal row of a two-stage table was tested from its expert's, found
    through the ``expert_<modality>`` tag. None when it is not on this machine."""
    tags = run.data.tags
    own = best_checkpoint(tags.get("table", ""), tags.get("config_hash", ""))
    if own.exists():
        return own
    if "reused_from" in tags:
        return row_checkpoint(tracker, tracker.get_run(tags["reused_from"]))
    experts = [v for k, v in tags.items() if k.startswith("expert_")]
    if len(experts) == 1:
        expert_tags = tracker.get_run(experts[0]).data.tags
        expert = best_checkpoint(expert_tags.get("table", ""), expert_tags.get("config_hash", ""))
        return expert if expert.exists() else None
    return None


def no_checkpoint(seeds: pd.DataFrame) -> str:
    """Why none of a row's runs ``seeds`` has a checkpoint on this machine, in words for the log."""
    if loaded_runs(seeds).all():
        return "its runs were loaded from published records: no checkpoint here"
    return "no checkpoint of its runs here"


def row_model(cfg: DictConfig, ckpt: Path | None) -> torch.nn.Module:
    """The model of a row's job config with the weights of ``ckpt`` (None: its initial weights, which time the
    same for these dense networks). A single-modal row of a two-stage table is its expert's model."""
    if cfg.get("experts") and cfg.stage.get("name") == "single":
        cfg = expert_config(cfg, cfg.stage.modality)
    return load_model(cfg, ckpt) if ckpt is not None else instantiate(cfg.model)


def first_test_sample(cfg: DictConfig) -> dict:
    """The first test frame of the row's inputs, at batch 1."""
    datamodule = instantiate(cfg.data)
    datamodule.setup("test")
    batch = next(iter(datamodule.test_dataloader()))
    return {k: v[:1] for k, v in batch.items() if torch.is_tensor(v)}


def measure(
    cfg: DictConfig,
    tracker: Tracker,
    compose: Callable[[list[str]], DictConfig],
    overrides: Sequence[str] = (),
    only_if_missing: bool = False,
) -> dict[str, dict[str, float]]:
    """Time every row of ``cfg.table`` that has FINISHED runs, side by side, and log the figures to its runs.
    Returns {row: figures}. ``only_if_missing`` (a sweep's end): do nothing when every run already has its
    figures, so a sweep that trained nothing leaves the table as it was; else all rows are timed again together."""
    opts = cfg.comp_time
    table = table_spec(cfg)
    runs = collect(tracker, table.name)
    if runs.empty:
        log.warning("Latency: no finished runs of table '%s'", table.name)
        return {}
    device = timing_device(str(opts.device))
    torch.set_num_threads(int(opts.threads))
    if only_if_missing and "latency_ms" in runs and runs["latency_ms"].notna().all():
        log.info("Latency: every row of '%s' is timed already", table.name)
        return {}
    if not table.rows:
        log.warning("Latency: table '%s' names no rows (an ad-hoc sweep); time an experiment's table", table.name)
        return {}
    order = [spec["row"] for spec in table.rows]
    rows = [r for r in order if r in set(runs["row"])]
    forwards, figures, checkpoints = load_rows(rows, runs, tracker, compose, overrides, device)
    load_start, cores = machine_load()
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)
    with torch.inference_mode():
        times = interleaved(forwards, int(opts.repeats), int(opts.warmup), sync=sync)
    load_end, _ = machine_load()
    for row, ts in times.items():
        q1, med, q3 = quartiles(ts)
        load = max(load_start, load_end)
        figures[row].update(
            latency_ms=med, latency_q1_ms=q1, latency_q3_ms=q3, latency_load=load, latency_cores=float(cores)
        )
        tags = {
            "latency_threads": str(opts.threads),
            "latency_device": str(device),
            "latency_checkpoint": checkpoints[row],
        }
        for run_id in runs.loc[runs["row"] == row, "run_id"]:
            tracker.log_metrics(run_id, figures[row])
            tracker.set_tags(run_id, tags)
    if max(load_start, load_end) > cores:
        log.warning(
            "Latency: load average %.1f / %.1f (start / end) exceeds the %d available cores",
            load_start,
            load_end,
            cores,
        )
    return figures


def timing_device(option: str) -> torch.device:
    """``comp_time.device``: ``auto`` is a GPU where there is one, else the CPU."""
    if option == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(option)


def load_rows(
    rows: list[str],
    runs: pd.DataFrame,
    tracker: Tracker,
    compose: Callable[[list[str]], DictConfig],
    overrides: Sequence[str],
    device: torch.device,
) -> tuple[dict[str, Callable[[], object]], dict[str, dict[str, float]], dict[str, str]]:
    """Each row's model (the checkpoint of its lowest seed that has one here, else its lowest seed's initial
    weights) on its first test frame: {row: forward pass}, {row: params and MACs}, {row: the checkpoint it was
    loaded from}. A run loaded from published records (``python -m ablate.report --extend``) has no checkpoint
    here, so a row's seeds trained in this store are timed before it."""
    forwards: dict[str, Callable[[], object]] = {}
    figures: dict[str, dict[str, float]] = {}
    checkpoints: dict[str, str] = {}
    for row in rows:
        seeds = runs[runs["row"] == row].sort_values("seed")
        first, ckpt = seeds.iloc[0], None
        for _, run in seeds.iterrows():
            if (ckpt := row_checkpoint(tracker, tracker.get_run(run["run_id"]))) is not None:
                first = run
                break
        rcfg = compose(list(overrides) + [f"row={row}", f"seed={first['seed']}"])
        model = row_model(rcfg, ckpt).to(device).eval()
        sample = {k: v.to(device) for k, v in first_test_sample(rcfg).items()}
        log.info("Latency: %s from %s", row, ckpt or f"initial weights ({no_checkpoint(seeds)})")
        checkpoints[row] = str(ckpt or "none")
        figures[row] = {
            "params_m": sum(p.numel() for p in model.parameters()) / 1e6,
            "macs_g": macs(model, sample) / 1e9,
        }
        forwards[row] = (lambda m, s: lambda: m(s))(model, sample)
    return forwards, figures, checkpoints


def main(argv: list[str] | None = None) -> int:
    """``python -m ablate.latency experiment=<table> [key=value ...]``, its arguments read by
    :func:`ablate.cli.latency` (``--help`` and a bad option end the process there, status 0 and 2): time the table's
    rows, log the figures to their runs and rewrite the table; 1 where the store has no runs of the table."""
    args = cli.latency(__doc__, argv).overrides
    try:
        cfg = compose_root(args)
    except HydraException as err:  # experiment=<unknown>, or a user's config without its hydra.searchpath
        print(f"error: {composition_error(err)}", file=sys.stderr)
        return 1
    tracker = Tracker.from_config(cfg)
    if tracker.find_experiment(cfg.table.name) is None:
        print(f"error: no runs for table '{cfg.table.name}' in {tracker.uri}", file=sys.stderr)
        return 1
    figures = measure(cfg, tracker, compose_root, args)
    for row, f in figures.items():
        print(
            f"{row:24s} {f['latency_ms']:9.2f} ms  [{f['latency_q1_ms']:.2f}, {f['latency_q3_ms']:.2f}]  "
            f"{f['params_m']:.2f} M params  {f['macs_g']:.2f} GMACs"
        )
    for path in published.publish(cfg, tracker, None, fingerprint.compute):  # an explicit rewrite
        print(path)
    return 0
