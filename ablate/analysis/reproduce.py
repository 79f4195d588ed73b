"""``python -m ablate.report --reproduce experiment=<table> row=<row> [seed=N]``: does a row's number hold here?

It reruns one seed of the row (its first recorded seed unless ``seed=`` says) at today's code, in a scratch launch
directory and store (so no checkpoint of the recorded run is resumed; the generated data is shared through a link,
being the same files), and says:

* whether the new value lies inside the row's 95 % *prediction interval for a new seed*, ``mean ± t(0.975, n-1) ·
  s · sqrt(1 + 1/n)`` over the recorded seeds (:func:`ablate.tables.significance.prediction_interval`): the range a
  single new run should fall in, wider than the CI of the mean; where the rerun's numerics differ from the recorded
  runs' and the table measured how far other numerics move a run (``table.kernels_run``), wider by that too;
* how far it is from the recorded run of the same seed;
* where this machine, the precision or the thread count differ from the recorded runs' own: the numerics are a
  source of variation of their own (Bouthillier et al. 2021).

A row raced on the config a tuning phase chose for it (its records' ``tuned_config``, :mod:`ablate.sweep.tuning`)
is rerun on that config: each tuned value that differs from the composed config's is set again, under ``draws``
(the experts' under ``experts.draws.<modality>``), as the sweep set it.

The recorded runs are the table's published records (``results/runs/<table>.csv``, :mod:`ablate.tables.records`)
where it has them, so the check works on a fresh clone; else the runs of the store the config names.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd
from omegaconf import DictConfig, OmegaConf

from ablate.config import compose
from ablate.jobs.spec import apply_draws
from ablate.store import Tracker, split_tuned_key
from ablate.tables import collect, published, table_spec
from ablate.tables.collect import under_condition
from ablate.tables.columns import kernels_run
from ablate.tables.records import numerics_differ, read_records
from ablate.tables.significance import prediction_interval


@dataclass
class Reproduction:
    row: str
    seed: int
    key: str
    value: float
    recorded: float | None  # the recorded run of the same seed
    values: list[float]  # every recorded seed of the row
    interval: tuple[float, float]
    differences: list[str]  # the numerics that differ from the recorded runs'
    tuned: list[str] = field(default_factory=list)  # the overrides that put the rerun on the row's tuned config
    resumed: str = ""  # the step the recorded run resumed from a checkpoint at ("" uninterrupted, "?" not recorded)
    rounding: tuple[float, int] | None = None  # other numerics' sd and seeds, where the interval adds them

    @property
    def inside(self) -> bool:
        lo, hi = self.interval
        return bool(lo <= self.value <= hi)

    def lines(self) -> list[str]:
        lo, hi = self.interval
        n = len(self.values)
        head = f"{self.row}, seed {self.seed}, {self.key}: {self.value:.2f} rerun here"
        if self.recorded is not None:
            head += f"; recorded {self.recorded:.2f} ({self.value - self.recorded:+.2f})"
        if np.isnan(lo):
            verdict = f"no prediction interval: the row has {n} recorded seed(s), it needs 2"
        else:
            other = (
                f", widened by other numerics' sd {self.rounding[0]:g} (over {self.rounding[1]} seeds, table.kernels_run)"
                if self.rounding
                else ""
            )
            verdict = (
                f"{'inside' if self.inside else 'OUTSIDE'} the row's 95 % prediction interval for a new seed "
                f"[{lo:.2f}, {hi:.2f}] (mean {np.mean(self.values):.2f} over {n} recorded seeds{other})"
            )
        out = [head, verdict]
        if self.tuned:
            out.append(f"rerun on the row's tuned config: {' '.join(self.tuned)}")
        if self.resumed == "?":
            out.append("whether the recorded run was resumed is not recorded (its records predate resumed_step)")
        elif self.resumed:
            out.append(
                f"the recorded run was resumed from a checkpoint at step {self.resumed}; the rerun trained uninterrupted"
            )
        out += [f"differs from the recorded runs: {d}" for d in self.differences] or [
            "same CPU, precision and threads as the recorded runs"
        ]
        if self.differences and not self.rounding and not np.isnan(lo):
            out.append(
                "the table has not measured how far other numerics move a run (table.kernels_run, "
                "bench/kernel_spread.py): the interval is another seed's on the recorded numerics"
            )
        return out


def tuned_config(runs: pd.DataFrame, cfg: DictConfig) -> list[str]:
    """The overrides that put a rerun of a row on the config its recorded ``runs`` were tuned to: each tuned value
    that differs from ``cfg``'s (an unset value, a recipe's default, is left as the recipe has it), and each value
    its experts were tuned to (:func:`ablate.store.split_tuned_key`); a row whose runs
    were tuned to different configs is refused (:func:`ablate.tables.tuning.check_tuned`)."""
    if "tuned_config" not in runs:
        return []
    configs = sorted({str(c) for c in runs["tuned_config"].fillna("") if str(c)})
    if len(configs) > 1:
        raise ValueError(f"the row's recorded runs were tuned to different configs: {'; '.join(configs)}")
    out = []
    for key, value in json.loads(configs[0]).items() if configs else []:
        modality, name = split_tuned_key(key)
        if value is None or (modality is None and value == OmegaConf.select(cfg, name)):
            continue  # an expert's value is recorded only where the sweep set it: always set again
        out.append(f"++experts.draws.{modality}.{name}={value}" if modality else f"++draws.{name}={value}")
    return out


def recorded_config(runs: pd.DataFrame, base: list[str]) -> Callable[[str], DictConfig]:
    """The config of a recorded run, composed today from its table, row, seed and scale, on the config a tuning
    phase chose for its row (the records' ``tuned_config``, applied as its job applied it): records keep no
    config; a row whose config changed since has another config hash, which the footer's fingerprint check sees."""
    by_id = runs.set_index("run_id")

    def config(run_id: str) -> DictConfig:
        run = by_id.loc[run_id]
        overrides = base + [f"row={run['row']}", f"seed={run['seed']}", f"scale={run['scale']}"]
        cfg = compose(overrides)
        tuned = tuned_config(runs[runs["row"] == run["row"]], cfg)
        if tuned:
            cfg = compose(overrides + tuned)
            apply_draws(cfg)
        return cfg

    return config


def published_configs(
    table: str, rows: Mapping[str, list[str]], compose: Callable[[list[str]], DictConfig]
) -> dict[str, list[str]]:
    """``table.tuned_from=published``: per row of ``rows`` (row -> its jobs' overrides), what puts its jobs on the
    config its published records were tuned to (:func:`tuned_config`, and ``tuned=published``, so that the runs
    record their tuned values), so that one command races the published table's rows on their published configs.
    A table without published records, or a row it lacks, is one ValueError naming them."""
    path = published.records(table)
    if not path.exists():
        raise ValueError(f"table.tuned_from=published: {table} has no published records ({path})")
    published.check(table)
    runs = read_records(path)
    out = {}
    for row, overrides in rows.items():
        mine = runs[runs["row"] == row]
        if not len(mine):
            raise ValueError(f"table.tuned_from=published: row {row} is not in {path}")
        try:
            out[row] = [*tuned_config(mine, compose(list(overrides))), "tuned=published"]
        except ValueError as err:
            raise ValueError(f"table.tuned_from=published: row {row}: {err}") from None
    return out


def rerun(overrides: list[str], launch: Path, scratch: Path) -> None:
    """Run ``python -m ablate <overrides>`` in ``scratch`` with a store of its own, its data linked to the launch
    directory's; raise with the job's exit status when it fails."""
    scratch.mkdir(parents=True, exist_ok=True)
    data = launch / "data"
    if data.is_dir() and not (scratch / "data").exists():
        (scratch / "data").symlink_to(data, target_is_directory=True)
    env = {**os.environ, "MLFLOW_TRACKING_URI": f"sqlite:///{scratch / 'mlflow.db'}"}
    code = subprocess.call([sys.executable, "-m", "ablate", *overrides], cwd=scratch, env=env)
    if code:
        raise RuntimeError(f"the rerun failed (exit {code}); its log is under {scratch / 'outputs'}")


def recorded_runs(cfg: DictConfig, table: DictConfig) -> tuple[pd.DataFrame, str]:
    """The runs a row's rerun is compared with, and where they come from: the published records of the table
    (``results/runs/<table>.csv``, so the check works on a fresh clone; records that are not what was published
    raise :class:`~ablate.tables.seal.BrokenRecords`), else the runs of the store ``cfg`` names."""
    path = published.records(str(table.name))
    if path.exists():
        published.check(str(table.name))
        return under_condition(read_records(path), table), str(path)
    tracker = Tracker.from_config(cfg)
    return under_condition(collect(tracker, str(table.name)), table), tracker.uri


def reproduce(cfg: DictConfig, overrides: list[str], keep: Path | None = None) -> Reproduction:
    """Rerun one seed of ``cfg``'s row (``row=`` among ``overrides``) and compare it with the row's published
    records (:func:`recorded_runs`)."""
    table = table_spec(cfg)
    row = next((o.split("=", 1)[1] for o in overrides if o.startswith("row=")), None)
    if row is None:
        raise ValueError("--reproduce needs row=<row> (one of the table's rows)")
    runs, source = recorded_runs(cfg, table)
    mine = runs[runs["row"] == row] if len(runs) else runs
    if not len(mine) or table.primary not in mine:
        raise ValueError(f"no FINISHED runs of row '{row}' of {table.name} in {source}")
    by_seed = {int(s): float(v) for s, v in zip(mine["seed"], mine[table.primary]) if str(s).isdigit()}
    given = [o for o in overrides if o.startswith("seed=")]
    seed = int(given[0].split("=", 1)[1]) if given else min(by_seed)
    rest = [o for o in overrides if not o.startswith("seed=")]
    tuned = tuned_config(mine, cfg)
    with tempfile.TemporaryDirectory(prefix="ablate-reproduce-") as tmp:
        scratch = keep or Path(tmp)
        rerun([*rest, *tuned, f"seed={seed}"], Path.cwd(), scratch)
        fresh = Tracker(f"sqlite:///{scratch / 'mlflow.db'}")
        new = under_condition(collect(fresh, str(table.name)), table)
        new = new[(new["row"] == row) & (new["seed"].astype(str) == str(seed))]
        if not len(new):
            raise RuntimeError(f"the rerun of {row} seed {seed} recorded no FINISHED run")
    values = list(by_seed.values())
    differences = numerics_differ(mine, new.iloc[:1])
    rounding = kernels_run(table) if differences else None
    return Reproduction(
        row,
        seed,
        str(table.primary),
        float(new[table.primary].iloc[0]),
        by_seed.get(seed),
        values,
        prediction_interval(values, rounding),
        differences,
        tuned,
        recorded_resume(mine, seed),
        rounding,
    )


def recorded_resume(mine: pd.DataFrame, seed: int) -> str:
    """The step the recorded run of ``seed`` resumed at: "" uninterrupted, "?" where the records do not say."""
    if "resumed_step" not in mine:
        return "?"
    step = mine.loc[mine["seed"].astype(str) == str(seed), "resumed_step"].fillna("").astype(str)
    return "" if not len(step) or step.iloc[0] in ("", "0") else step.iloc[0]
