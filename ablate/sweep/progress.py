"""A sweep's overall progress: jobs finished of planned, and an ETA from the finished jobs' durations.

The sweep writes how many jobs it plans (``<sweep dir>/.planned``, from the same splitting of the overrides that
Hydra's basic sweeper does); every job, in whichever process runs it, appends its outcome and duration to
``<sweep dir>/.progress`` under a file lock and logs one line such as
``Sweep progress: 4/9 jobs finished (1 skipped), 5 to go, ETA 11 min (2.2 min per trained job, 2 at a time)``.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from pathlib import Path

from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
from hydra.core.override_parser.overrides_parser import OverridesParser
from omegaconf import DictConfig, OmegaConf

from ablate.config import compose
from ablate.store import file_lock, row_name
from ablate.sweep.tuning import Experts, TuneSpec, choices
from ablate.tables.spec import LOWER_IS_BETTER, sweep_params

PLANNED_FILE = ".planned"
PROGRESS_FILE = ".progress"


def job_overrides(config: DictConfig, objectives: Mapping[str, Mapping[int, float]] | None = None) -> list[list[str]]:
    """Every job's overrides, as the multirun of ``config`` launches them: the product of its swept values (the
    sweeper's ``params``, a table's rows and the command line together, a key on the command line winning), as
    Hydra's basic sweeper splits them; for a table that races its seeds (``table.seeds``), each with the seeds of its
    first look, after its tuning trials where it tunes (``table.tune``, :mod:`ablate.sweep.tuning`). Given the
    tuning trials' ``objectives`` in the store (row -> trial -> value: a resumed sweep's), stage 2's trials sit on
    the experts' chosen draws and the raced jobs on their rows' chosen trials, as the sweeper launches them once it
    has chosen (:func:`ablate.sweep.tuning.choices`)."""
    params = OmegaConf.select(config, "hydra.sweeper.params", default=None) or {}
    arguments = list(config.hydra.overrides.task)
    params = sweep_params(params, arguments, config.table)  # a table's rows (ablate.tables.spec.run_rows)
    lines = [f"{key}={value}" for key, value in params.items()] + arguments
    overrides = OverridesParser.create().parse_overrides(lines)
    jobs = [list(job) for batch in BasicSweeper.split_arguments(overrides, None) for job in batch]
    looks = OmegaConf.select(config, "table.seeds.looks", default=None)
    seeded = any(o.get_key_element().lstrip("+~") == "seed" for o in overrides)
    if not looks or seeded:
        return jobs
    tune = OmegaConf.select(config, "table.tune", default=None)
    spec = TuneSpec.from_config(OmegaConf.to_container(tune, resolve=True) if tune else None)  # type: ignore[arg-type]
    name = str(OmegaConf.select(config, "table.name", default=""))
    swept = {o.get_key_element().lstrip("+~") for o in overrides if o.is_sweep_override()}
    rows = {row_name(job, swept): job for job in jobs}  # as the racing sweeper names them
    trials: list[list[str]] = []
    raced: dict[str, list[str]] = {row: [] for row in rows}
    if spec is not None:  # the experts' trials first, where rows sit on experts; a single-modal row is its expert
        experts = Experts.of(rows, compose) if spec.experts else Experts()
        fixed: list[str] = []
        if objectives:  # a resumed phase: what it chose so far
            higher = str(OmegaConf.select(config, "table.primary", default="")) not in LOWER_IS_BETTER
            tuned = choices(spec, name, rows, experts, objectives, (spec.trials, spec.trials), higher)
            fixed, raced = tuned.fixed, tuned.overrides
        stage2 = [[*job, *fixed] for row, job in rows.items() if row not in experts.single]
        for part in (list(experts.trials().values()), stage2):  # every expert trial before stage 2, as the phase runs
            trials += [[*job, *spec.overrides(name, k)] for k in range(spec.trials) for job in part]
    return trials + [[*job, *raced[row], f"seed={seed}"] for row, job in rows.items() for seed in range(int(looks[0]))]


def planned_jobs(config: DictConfig) -> int:
    """How many jobs the multirun of ``config`` launches (:func:`job_overrides`; a race's first look: each later
    look replans, :func:`replan`)."""
    return len(job_overrides(config))


def replan(sweep_dir: Path, planned: int) -> None:
    """Record a new planned job count (a race's next look adds jobs)."""
    (sweep_dir / PLANNED_FILE).write_text(str(planned))


def start(sweep_dir: Path, config: DictConfig) -> int:
    """Record the planned job count of the sweep in ``sweep_dir``; return it."""
    planned = planned_jobs(config)
    (sweep_dir / PLANNED_FILE).write_text(str(planned))
    (sweep_dir / PROGRESS_FILE).write_text("")
    return planned


def finished(sweep_dir: Path, status: str, seconds: float, parallel: int = 1) -> str:
    """Record one job's end (``status``: FINISHED, SKIPPED, FAILED; its wall ``seconds``) and return the sweep's
    progress line."""
    path = sweep_dir / PROGRESS_FILE
    with file_lock(sweep_dir / ".progress.lock"):
        with open(path, "a") as handle:
            handle.write(json.dumps({"status": status, "seconds": round(seconds, 3)}) + "\n")
        records = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    planned_file = sweep_dir / PLANNED_FILE
    planned = int(planned_file.read_text()) if planned_file.exists() else len(records)
    return summary(records, planned, parallel)


def summary(records: list[dict], planned: int, parallel: int = 1) -> str:
    """The progress line for the finished jobs' ``records`` of ``planned``, ``parallel`` jobs at a time. The ETA
    takes the trained jobs' mean duration for every job to go (a skipped job costs nothing, but which of the rest
    will be skipped is not known)."""
    done = len(records)
    skipped = sum(r["status"] == "SKIPPED" for r in records)
    failed = sum(r["status"] == "FAILED" for r in records)
    notes = ", ".join(f"{n} {word}" for n, word in ((skipped, "skipped"), (failed, "failed")) if n)
    line = f"Sweep progress: {done}/{planned} jobs finished" + (f" ({notes})" if notes else "")
    left = max(planned - done, 0)
    trained = [r["seconds"] for r in records if r["status"] != "SKIPPED"]
    if left and trained:
        mean = sum(trained) / len(trained)
        eta = math.ceil(left / max(parallel, 1)) * mean
        line += f", {left} to go, ETA {_minutes(eta)} ({_minutes(mean)} per trained job, {max(parallel, 1)} at a time)"
    elif left:
        line += f", {left} to go"
    return line


def _minutes(seconds: float) -> str:
    return f"{seconds:.0f} s" if seconds < 90 else f"{seconds / 60:.1f} min"
