"""Where fusion can gain over the single-modal experts, and where its gates look: ``python -m ablate.diagnose``.

This module finds a two-stage table's trained checkpoints and runs and hands each model to its task family's
diagnosis; SMoE's instance tables are the family that has one (:mod:`ablate.tasks.yolact.diagnose`, its tables and
figures :mod:`ablate.tasks.yolact.diagnosis_report`).

SMoE's claim (seed 000 §5.1, Table 1) is that fusing the RGB and the DDM experts beats both. Whether it can on
given data depends on what the experts know that the other does not. For every seed of a two-stage table
(default ``experiment=smoe_table1``; any ``key=value`` override applies, e.g. ``scale=smoke``) this evaluates the
trained checkpoints on the test split:

* recall of every counted ground-truth object (the AP's objects: >= 25 px tall at KITTI's height, see
  :class:`~ablate.metrics.coco.MaskAP`) per condition group: found = a detection of its class, among all the
  detections AP sees, with mask IoU >= 0.5. For the RGB and DDM experts, their union (objects either expert finds:
  what a fusion could recover without learning anything new) and "RGB only" (found by RGB, missed by DDM: the
  room fusion has over the better expert), and for every fused row;
* the mean gate weight on each modality per condition group and fusion point (rows with a gated operator;
  SMoE eq. 2-3: W on f_i = RGB, 1 - W on f_j = DDM), averaged over channels and positions;
* the validation AP per epoch of each expert, from MLflow: whether an expert was still learning when it stopped;
* the experts' mask AP in clear weather, at night and in glare on the *same* test frames (each condition applied
  to all of them, so the columns differ by the condition only, not by which frames drew it), and the checks a
  dataset must pass before fused rows mean anything (:data:`CHECKS`): RGB in clear weather at least 0.6x DDM;
  objects found by RGB only and by DDM only each >= 10 %; the union >= 10 points above the better expert; night
  and glare lower the RGB expert's AP clearly (by >= 20 %) while the DDM expert's stays within 10 % of its
  clear-weather AP.

``row=x,y`` diagnoses those rows of the table only (a table swept on some of its rows, ``python -m ablate -m
experiment=smoe_table1 row=x,y``). ``experts_only=true`` evaluates the single-modal rows only: the data check,
before any fused row is trained (written to ``results/<table>_experts.md`` / ``.png``).

Writes ``results/<table>_diagnosis.md`` and ``.png``, and two figures of seed 0: ``<table>_masks.png`` (SMoE Fig.
6: ground truth and every row's masks on the busiest frame of each condition) and ``<table>_gates.png`` (the gate
maps of the table's last gated row on a night and a glare frame). Needs the table's checkpoints (``checkpoints/``,
kept by ``python -m ablate -m experiment=...``): a missing one is named with the command that makes it.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import pandas as pd  # noqa: E402
from hydra.errors import HydraException  # noqa: E402
from hydra.utils import instantiate  # noqa: E402
from omegaconf import DictConfig  # noqa: E402
from tqdm import tqdm  # noqa: E402

from ablate import cli  # noqa: E402
from ablate.config import compose, composition_error  # noqa: E402
from ablate.jobs.experts import EXPERTS_TABLE, expert_config, load_model  # noqa: E402
from ablate.jobs.spec import CHECKPOINTS, best_checkpoint  # noqa: E402
from ablate.store import Tracker, config_hash  # noqa: E402
from ablate.tables import published  # noqa: E402
from ablate.tables.raceplan import RacePlan  # noqa: E402
from ablate.tasks.yolact.diagnose import ap_per_condition, evaluate  # noqa: E402
from ablate.tasks.yolact.diagnosis_report import masks_figure, plot, to_markdown  # noqa: E402

#: The task families that have a diagnosis (the ``_target_`` of ``cfg.task``).
DIAGNOSED = ("ablate.tasks.instance.InstanceTask",)


class MissingCheckpoint(FileNotFoundError):
    pass


def checkpoint(cfg: DictConfig, table: str, row: str = "?") -> Path:
    """The best checkpoint of a job: its expert's for a single-modal row of a two-stage table, else the job's own
    (looked up under every table, since a row shared by two tables is trained once)."""
    if cfg.stage.name == "single" and cfg.get("experts"):
        chash = config_hash(expert_config(cfg, cfg.stage.modality))
        found = [best_checkpoint(EXPERTS_TABLE, chash)]
    else:
        chash = config_hash(cfg)
        found = sorted(CHECKPOINTS.glob(f"*/{chash}/best.ckpt"))
    found = [p for p in found if p.exists()]
    if not found:
        raise MissingCheckpoint(
            f"no checkpoint for row {row} seed {cfg.seed} (config {chash}) "
            f"under {CHECKPOINTS.resolve()}: run `python -m ablate -m experiment={table}` "
            "with the same overrides first"
        )
    return found[0]


def expert_curves(tracker: Tracker, experts: dict[tuple[int, str], DictConfig]) -> pd.DataFrame:
    """Validation AP per epoch of each expert (seed, modality), from the MLflow experiment ``experts``."""
    exp = tracker.find_experiment(EXPERTS_TABLE)
    out = []
    for (seed, modality), ecfg in experts.items():
        query = f"attributes.status = 'FINISHED' and tags.config_hash = '{config_hash(ecfg)}'"
        runs = [] if exp is None else tracker.runs(exp, query)
        if runs:
            history = tracker.metric_history(runs[0].info.run_id, "val/map")
            out += [{"seed": seed, "modality": modality, "step": h.step, "val_map": h.value} for h in history]
    return pd.DataFrame(out, columns=["seed", "modality", "step", "val_map"])


def diagnose(overrides: list[str], experts_only: bool = False, rows: list[str] | None = None) -> dict[str, Any]:
    """Evaluate every row of the table, or the ``rows`` named (only its single-modal rows with ``experts_only``),
    for the seeds every row has (the race's first look, :meth:`~ablate.tables.raceplan.RacePlan.first`); returns
    the per-object and gate frames, the experts' curves and their AP per condition."""
    base = compose(overrides)
    table = base.table
    if unknown := sorted(set(rows or []) - {str(spec.row) for spec in table.rows}):
        raise ValueError(f"row={','.join(unknown)}: not a row of {table.name}")
    chosen = [spec for spec in table.rows if not rows or spec.row in rows]
    if not base.get("experts"):
        raise ValueError(f"{table.name}: not a two-stage table (experts: null); nothing to compare fusion with")
    if str(base.task.get("_target_")) not in DIAGNOSED:
        raise ValueError(f"{table.name}: its task family ({base.task.get('_target_')}) has no diagnosis")
    plan = RacePlan.of_table(base)
    seeds = plan.first if plan is not None else 1
    found = Found()
    for seed, spec in tqdm([(s, r) for s in range(seeds) for r in chosen], desc=f"diagnose {table.name}"):
        cfg = compose(overrides + [f"row={spec.row}", f"seed={seed}"])
        if cfg.stage.name == "single":
            found.experts[(seed, cfg.stage.modality)] = expert_config(cfg, cfg.stage.modality)
        elif experts_only:
            continue
        found.add(cfg, seed, spec, checkpoint(cfg, table.name, spec.row))
    return found.result(table, expert_curves(Tracker.from_config(base), found.experts), experts_only)


class Found:
    """What the models of a table were found to do, collected row by row and seed by seed."""

    def __init__(self) -> None:
        self.objects: list[pd.DataFrame] = []
        self.gates: list[pd.DataFrame] = []
        self.experts: dict[tuple[int, str], DictConfig] = {}
        self.showcase: dict[str, Any] = {}
        self.gate_figure: Any = None
        self.conditions: list[dict[str, Any]] = []

    def add(self, cfg: DictConfig, seed: int, spec: DictConfig, ckpt: Path) -> None:
        """Evaluate one row's model of one seed on its test split."""
        datamodule = instantiate(cfg.data)
        datamodule.prepare_data()
        datamodule.setup("test")
        ev = evaluate(cfg, load_model(cfg, ckpt), datamodule)
        if cfg.stage.name == "single":
            self.conditions += [
                {"seed": seed, "modality": cfg.stage.modality, "condition": c, "map": v}
                for c, v in ap_per_condition(cfg, load_model(cfg, ckpt)).items()
            ]
        name = spec.get("name", spec.row)
        for frame, into in ((ev.objects, self.objects), (ev.gates, self.gates)):
            if len(frame):
                into.append(frame.assign(seed=seed, row=spec.row, name=name, modality_row=cfg.stage.get("modality")))
        if seed == 0:
            self.showcase[name] = ev.showcase
            if len(ev.gates) and ev.gate_batch is not None:  # the last gated row of the table wins
                if self.gate_figure is not None:
                    plt.close(self.gate_figure)
                self.gate_figure = ev.task.gate_figure(ev.gate_batch)

    def result(self, table: DictConfig, curves: pd.DataFrame, experts_only: bool) -> dict[str, Any]:
        return {
            "table": table,
            "objects": pd.concat(self.objects, ignore_index=True) if self.objects else pd.DataFrame(),
            "gates": pd.concat(self.gates, ignore_index=True) if self.gates else pd.DataFrame(),
            "curves": curves,
            "showcase": self.showcase,
            "gate_figure": self.gate_figure,
            "conditions": pd.DataFrame(self.conditions, columns=["seed", "modality", "condition", "map"]),
            "experts_only": experts_only,
        }


def main(argv: list[str] | None = None) -> int:
    """``python -m ablate.diagnose [experiment=<table>] [row=x,y] [experts_only=true] [key=value ...]``, its
    arguments read by :func:`ablate.cli.diagnose` (``--help`` and a bad option end the process there, status 0 and
    2): write the diagnosis and its figures; 1 where the table cannot be diagnosed here (a missing checkpoint)."""
    parsed = cli.diagnose(__doc__, argv)
    experts_only = parsed.experts_only
    try:
        result = diagnose(parsed.overrides, experts_only, parsed.row)
    except (MissingCheckpoint, ValueError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 1
    except HydraException as err:  # experiment=<unknown>, or a user's config without its hydra.searchpath
        print(f"error: {composition_error(err)}", file=sys.stderr)
        return 1
    name = result["table"].name
    stem = f"{name}_{'experts' if experts_only else 'diagnosis'}"
    print(published.write_text(f"{stem}.md", to_markdown(result)))
    figures = {f"{stem}.png": plot(result)}
    if not experts_only:
        figures[f"{name}_masks.png"] = masks_figure(result["showcase"])
    if result["gate_figure"] is not None:
        figures[f"{name}_gates.png"] = result["gate_figure"]
    for file, fig in figures.items():
        print(published.write_figure(file, fig))
    return 0
