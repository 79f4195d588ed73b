"""What a table says of its tuning phase (:mod:`ablate.sweep.tuning`): per row, the trial it raced on, that trial's
config and validation objective, the trials run and their CPU minutes; in its footer, the search space, N, the
tuning seed and the validation metric; and ``<table>_tuning.png``, each row's expected validation performance
against the number of trials (:mod:`ablate.tables.evp`), flagging rows whose curves cross ("the ranking depends on
the budget").

The trials are runs of kind ``trial`` (tags ``row``, ``trial``, ``trial_config``, ``tune_search``: the space and
the tuning seed; metric ``val_best``), kept beside
the table's records (``runs/<table>.trials.csv``) so that the section renders again without the store. A table
whose runs of one row were tuned to different configs (tag ``tuned_config``) is refused: its seeds would not be
seeds of one config.
"""

from __future__ import annotations

import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
from omegaconf import DictConfig  # noqa: E402

from ablate.store import KIND_TRIAL, VAL_CURVE, Tracker, split_tuned_key  # noqa: E402
from ablate.tables.collect import sweep_wall  # noqa: E402
from ablate.tables.evp import crossing, expected_max  # noqa: E402
from ablate.tables.records import RUNS_DIR  # noqa: E402
from ablate.tables.seal import write_csv  # noqa: E402

#: How an expert's tuning row is named (ablate.sweep.tuning.expert_row): ``expert <modality>``.
EXPERT_ROW = "expert "
COLUMNS = [
    "run_id", "row", "trial", "seed", "status", "val_best", "trial_config", "seconds", "cpu", "started", "search",
    "sweep_id", "rung", "val_curve",
]  # fmt: skip
#: A trial's rung in the records: its fraction of the recipe's epochs; the full budget (no rung) is 1.
FULL = 1.0


def trials_path(results_dir: str | Path, table: str) -> Path:
    return Path(results_dir) / RUNS_DIR / f"{table}.trials.csv"


def from_store(tracker: Tracker, table: str) -> pd.DataFrame:
    """The tuning trials of ``table`` in the store, finished or failed (:data:`COLUMNS`); empty without any."""
    exp = tracker.find_experiment(table)
    if exp is None:
        return pd.DataFrame(columns=COLUMNS)
    out = []
    for r in tracker.runs(exp, f"tags.kind = '{KIND_TRIAL}'"):
        if r.info.status not in ("FINISHED", "FAILED"):
            continue
        tags = r.data.tags
        seconds = ((r.info.end_time or r.info.start_time) - r.info.start_time) / 1000
        value = r.data.metrics.get("val_best", np.nan) if r.info.status == "FINISHED" else np.nan
        out.append([r.info.run_id, tags.get("row", "?"), int(tags.get("trial", -1)), tags.get("seed", "?"),
                    r.info.status, value, tags.get("trial_config", "{}"), seconds, tags.get("cpu", "?"),
                    r.info.start_time, tags.get("tune_search", ""), tags.get("sweep_id", ""),
                    float(tags.get("rung", FULL)), tags.get(VAL_CURVE, "")])  # fmt: skip
    return pd.DataFrame(out, columns=COLUMNS).sort_values("started", kind="stable").reset_index(drop=True)


def write_trials(trials: pd.DataFrame, results_dir: str | Path, table: str) -> Path | None:
    if trials.empty:
        return None
    return write_csv(trials.sort_values(["row", "trial"]), trials_path(results_dir, table))


def read_trials(results_dir: str | Path, table: str) -> pd.DataFrame:
    path = trials_path(results_dir, table)
    if not path.exists():
        return pd.DataFrame(columns=COLUMNS)
    trials = pd.read_csv(
        path, dtype={"trial_config": str, "search": str, "val_curve": str}, keep_default_na=False, na_values=[""]
    )
    trials = trials.reindex(columns=[*COLUMNS, *(c for c in trials if c not in COLUMNS)])  # older: no search, sweep
    return trials.fillna({"rung": FULL})  # older: every trial to the full budget, no curve


def check_tuned(runs: pd.DataFrame) -> None:
    """Refuse runs of one row tuned to different configs (their ``tuned_config`` tags differ), in one line."""
    if "tuned_config" not in runs:
        return
    for row, sel in runs.groupby("row"):
        configs = sorted({str(c) for c in sel["tuned_config"].fillna("")})
        if len(configs) > 1:
            shown = "; ".join(c or "untuned" for c in configs)
            raise ValueError(
                f"row {row}: its runs were tuned to different configs ({shown}); race it again on one "
                "(python -m ablate -m experiment=... force=true), or leave the other runs out of the store"
            )


def phase_wall(trials: pd.DataFrame) -> tuple[float, int]:
    """The tuning phase's wall time in minutes, and over how many sweeps: a phase resumed by a later sweep (the same
    command again, its finished trials skipped, :mod:`ablate.sweep.tuning`) counts each sweep's span, from its first
    trial's start to its last one's end, never the time between sweeps. Trials without a sweep (older records) are
    one span."""
    started = trials["started"].astype(float)
    return sweep_wall(started, started + 1000 * trials["seconds"].astype(float), trials.get("sweep_id"))


def with_rung(trials: pd.DataFrame) -> pd.DataFrame:
    """``trials`` with their ``rung`` column; trials made before successive halving trained to the full budget."""
    return trials if "rung" in trials else trials.assign(rung=FULL)


def last_trials(trials: pd.DataFrame, rung: float | None = None) -> pd.DataFrame:
    """The latest run of each (row, trial) at its furthest rung of successive halving (or at ``rung``, where given:
    the trials that reached it), a trial run again (a resumed phase) counted once, by row and trial: the same from
    the store as from the records."""
    if not len(trials):
        return trials
    rungs = with_rung(trials)["rung"].astype(float)
    if rung is not None:  # as the tag holds it (ablate.jobs.tags): six significant digits
        at = rungs == float(f"{float(rung):.6g}")
        trials, rungs = trials[at], rungs[at]
    order = trials.assign(_rung=rungs).sort_values("_rung", kind="stable")  # the furthest rung last, then the latest
    kept = order.drop_duplicates(["row", "trial"], keep="last").drop(columns="_rung")
    return kept.sort_values(["row", "trial"], kind="stable")


def rung_runs(trials: pd.DataFrame) -> pd.DataFrame:
    """The last run of each trial at each rung of successive halving: a promoted trial's rungs each took their time,
    a trial run again (a resumed phase) counts once; without rungs, :func:`last_trials`'s runs."""
    if not len(trials):
        return trials
    return with_rung(trials).drop_duplicates(["row", "trial", "rung"], keep="last")


def trial_objectives(tracker: Tracker, table: str, rung: float | None = None) -> dict[str, dict[int, float]]:
    """Per row, each tuning trial's objective in the store (its latest run's ``val_best``; NaN where it failed): at
    the full budget, or at ``rung`` of successive halving (its fraction of the recipe's epochs)."""
    trials = last_trials(from_store(tracker, table), FULL if rung is None else rung)
    out: dict[str, dict[int, float]] = {}
    for row, trial, value in zip(trials.get("row", []), trials.get("trial", []), trials.get("val_best", [])):
        out.setdefault(str(row), {})[int(trial)] = float(value)
    return out


def section(trials: pd.DataFrame, table: DictConfig, names: dict[str, str]) -> list[str]:
    """The markdown lines on the tuning phase: a table of the rows' chosen trials, the footer's sentence, and whether
    the rows' curves cross; without trials, why the table races on the recipe where it says (``table.untuned``),
    else none."""
    trials = with_rung(trials)
    every, trials = rung_runs(trials), last_trials(trials)
    if trials.empty:
        untuned = table.get("untuned")  # a table that races on the recipe says why (docs/tuning.md)
        return ["", f"No tuning phase: every row raced on the recipe, because {untuned}."] if untuned else []
    lines = ["", "Tuning (validation only; the race ran on each row's chosen trial):", ""]
    lines += [
        "| Row | Trials | Chosen trial | Its config | Its validation objective | CPU min |",
        "|:--|--:|--:|:--|--:|--:|",
    ]
    order = {row: i for i, row in enumerate(names)}  # the experts first (tuned first), then the table's rows in order

    def place(row: str) -> tuple[int, int, str]:
        return (0 if row.startswith(EXPERT_ROW) else 1, order.get(row, len(order)), row)

    cpu = every.groupby("row")["seconds"].sum() / 60  # every rung's run of a trial: a promoted trial resumes
    for row, sel in sorted(trials.groupby("row"), key=lambda kv: place(str(kv[0]))):
        scored = sel[sel["rung"].astype(float) == FULL].dropna(subset=["val_best"])  # the full budget's alone
        best = scored.sort_values(["val_best", "trial"], ascending=[False, True]).iloc[0] if len(scored) else None
        config = config_text(best["trial_config"]) if best is not None else "—"
        objective = f"{best['val_best']:.4g}" if best is not None else "—"
        chosen = str(int(best["trial"])) if best is not None else "0 (no trial scored)"
        lines.append(
            f"| {names.get(str(row), row)} | {len(sel)} | {chosen} | {config} | {objective} | {cpu[row]:.1f} |"
        )
    searches = [str(s) for s in trials.get("search", pd.Series(dtype=str)).dropna() if str(s)]
    search = json.loads(searches[0]) if searches else {}  # the records' own: older records have none
    space = dict(search.get("space") or {})
    tuned = sorted(json.loads(str(trials["trial_config"].iloc[0]) or "{}"))
    n = int(trials.groupby("row")["trial"].count().max())
    said = (
        "; ".join(f"{k} ~ {v}" for k, v in space.items()) + f", tuning seed {search.get('seed', 0)}"
        if space
        else ", ".join(tuned)
    )
    lines += ["", f"Tuned: {said}; N = {n} trials per row (trial 0 the recipe; the same draws for every row)."]
    wall, sweeps = phase_wall(every)
    span = (
        "each sweep's first trial's start to its last one's end, added up"
        if sweeps > 1
        else "the first trial's start to the last one's end"
    )
    lines += halving_lines(every)
    lines.append(
        f"The tuning phase: {len(trials)} trials, {every['seconds'].sum() / 60:.0f} CPU min, {wall:.0f} min of wall "
        f"time{f' over {sweeps} sweeps' if sweeps > 1 else ''} from {span} (before the race)."
    )
    experts = sorted({str(r) for r in trials["row"] if str(r).startswith(EXPERT_ROW)})
    if experts:
        lines.append(
            f"The experts' own recipe was tuned first, as rows of their own ({', '.join(experts)}), and kept fixed "
            "while stage 2 was tuned on them; a single-modal row is its expert and raced on its expert's choice."
        )
    if trials["val_best"].isna().groupby(trials["row"]).all().any():
        lines.append(
            "A row with no scored trial raced on its recipe: its trials failed, or (tuned with the experts' recipe "
            "untuned) it is an expert's own row, which trains nothing in a trial."
        )
    curves = curves_of(every)
    if crossing(curves):
        lines.append("**The rows' expected-validation curves cross: the ranking depends on the tuning budget.**")
    return lines


def halving_lines(trials: pd.DataFrame) -> list[str]:
    """Where the phase halved (:mod:`ablate.sweep.halving`): its rungs and how many trials per row reached each;
    none where every trial trained to the full budget."""
    trials = with_rung(trials)
    rungs = sorted({float(r) for r in trials["rung"]})
    if rungs == [FULL]:
        return []
    reached = [int(trials[trials["rung"].astype(float) == r].groupby("row")["trial"].nunique().max()) for r in rungs]
    shown = ", ".join(f"{n} at {r:.3g}" for r, n in zip(rungs, reached))
    return [
        f"Successive halving: trials per row at each rung (its fraction of the recipe's epochs): {shown}; a promoted "
        "trial resumed from its checkpoint, and the choice is the best of those that reached the full budget."
    ]


def evp_trials(trials: pd.DataFrame) -> pd.DataFrame:
    """The trials the expected-validation curves are drawn from: each trial's value at the full budget, or where
    the phase halved, at its first rung, the one every trial reached (the same budget for every value)."""
    first = min((float(r) for r in with_rung(trials)["rung"]), default=FULL)
    return last_trials(trials, first)


def config_text(text: str) -> str:
    """A trial's own tuned values, short; a stage-2 trial's experts' values (``experts.<modality>.<key>``,
    :func:`ablate.store.tuned_key`) are their own rows' chosen trials, so they are named, not repeated."""
    values = [(split_tuned_key(k), v) for k, v in json.loads(text or "{}").items()]
    shown = [f"{name.rsplit('.', 1)[-1]}={'default' if v is None else v}" for (m, name), v in values if m is None]
    experts = sorted({m for (m, _), _ in values if m is not None})
    on = f" (on the experts' chosen trials: {', '.join(experts)})" if experts else ""
    return (", ".join(shown) or "the recipe") + on


def curves_of(trials: pd.DataFrame) -> dict[str, np.ndarray]:
    """Each row's expected validation performance against the number of trials (:func:`expected_max`)."""
    out = {}
    for row, sel in evp_trials(trials).groupby("row", sort=False):
        values = [float(v) for v in sel.sort_values("trial")["val_best"]]
        if any(not np.isnan(v) for v in values):
            out[str(row)] = expected_max(values)[0]
    return out


def write_figure(trials: pd.DataFrame, table: DictConfig, names: dict[str, str], out: Path) -> Path | None:
    """``<table>_tuning.png``: each row's expected best validation value against the number of trials, with one
    standard deviation as a band; None without trials."""
    trials = evp_trials(trials)
    if trials.empty:
        return None
    fig, ax = plt.subplots(figsize=(6.0, 3.6))
    for row, sel in trials.groupby("row", sort=False):
        values = [float(v) for v in sel.sort_values("trial")["val_best"]]
        if all(np.isnan(v) for v in values):
            continue
        mean, std = expected_max(values)
        n = np.arange(1, len(mean) + 1)
        ax.plot(n, mean, marker="o", label=names.get(str(row), str(row)))
        ax.fill_between(n, mean - std, mean + std, alpha=0.15)
    ax.set_xlabel("trials (random draws; trial 0 the recipe)")
    ax.set_ylabel("expected best validation value")
    ax.set_title(f"{table.title}: expected validation performance", fontsize=9)
    ax.legend(fontsize=7)
    fig.tight_layout()
    path = out / f"{table.name}_tuning.png"
    fig.savefig(path, dpi=100, metadata={"Software": None})
    plt.close(fig)
    return path
