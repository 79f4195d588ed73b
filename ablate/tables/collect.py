"""The runs of a table, from the store, as a pandas frame: one row per (table row, seed)."""

from __future__ import annotations

import pandas as pd
from mlflow.exceptions import MlflowException
from omegaconf import DictConfig

from ablate.store import KIND_JOB, SKIPPED_FRAMES, Tracker
from ablate.tables.records import LOADED

#: The run tags that say where and how a row was computed (ablate.hardware.tags), for the footer.
MADE = ("cpu", "precision", "threads")


def collect(tracker: Tracker, table: str) -> pd.DataFrame:
    """One row per (row, seed) of ``table``: its latest FINISHED job run, at the scale of the latest such run.

    A rerun after a config change (another recipe, another dataset) supersedes the earlier run of the same row and
    seed instead of counting as one more seed; runs at another scale (a smoke sweep beside the default-scale table)
    stay in the store and out of the table."""
    return latest(job_runs(tracker, table))


def latest(runs: pd.DataFrame) -> pd.DataFrame:
    """Of :func:`job_runs`' frame, the latest run per (row, seed) at the latest scale: what :func:`collect` gives."""
    df = at_latest_scale(runs)
    return df.drop_duplicates(["row", "seed"], keep="last").reset_index(drop=True) if len(df) else df


def at_latest_scale(runs: pd.DataFrame) -> pd.DataFrame:
    """The runs (oldest first) at the scale of the latest of them: a smoke sweep beside a table stays out of it."""
    return runs[runs["scale"] == runs["scale"].iloc[-1]] if len(runs) else runs


def job_runs(tracker: Tracker, table: str) -> pd.DataFrame:
    """Every FINISHED job run of ``table``, oldest first: one row per run, superseded ones too."""
    exp = tracker.find_experiment(table)
    if exp is None:
        return pd.DataFrame()
    runs = tracker.runs(exp, f"attributes.status = 'FINISHED' and tags.kind = '{KIND_JOB}'")
    records = [
        {
            "row": r.data.tags.get("row", "?"),
            "seed": r.data.tags.get("seed", "?"),
            "scale": r.data.tags.get("scale", "?"),
            "config_hash": r.data.tags.get("config_hash", r.info.run_id),
            "git_commit": r.data.tags.get("git_commit", "unknown"),
            "run_id": r.info.run_id,
            "evaluator": r.data.tags.get("evaluator", ""),
            "fingerprint": r.data.tags.get("fingerprint", ""),
            "job_num": int(r.data.tags.get("job_num", "0") or 0),
            "targets": " ".join(sorted({v for k, v in r.data.params.items() if k.endswith("_target_")})),
            **{f"made_{k}": r.data.tags.get(k, "?") for k in MADE},
            "cpu_isa": r.data.tags.get("cpu_isa", "?"),
            "cpu_kernels": r.data.tags.get("cpu_kernels", ""),
            "made_gpu": r.data.tags.get("gpu", ""),  # the GPU a job trained on (ablate.hardware.gpu); "" the CPU
            "sweep_id": r.data.tags.get("sweep_id", ""),
            "race_plan": r.data.tags.get("race_plan", ""),
            "tuned_config": r.data.tags.get("tuned_config", ""),  # the config a tuning phase chose for its row
            "reused_from": r.data.tags.get("reused_from", ""),
            "resumed_step": resumed_step(r.data.tags),
            LOADED: r.data.tags.get(LOADED, ""),  # a run loaded from a published record (ablate.analysis.extend)
            "started": r.info.start_time,
            # the job's start before its experts were trained (tag ``job_started``; older runs: the run's start)
            "job_started": int(r.data.tags.get("job_started") or r.info.start_time),
            "ended": r.info.end_time or r.info.start_time,
            **r.data.metrics,
        }
        for r in runs
    ]
    if not records:
        return pd.DataFrame()
    return pd.DataFrame.from_records(records).sort_values(["started", "config_hash"], kind="stable")


def row_seconds(tracker: Tracker, runs: pd.DataFrame) -> dict[str, float]:
    """Per row of a table's :func:`job_runs`, the median seconds one of its jobs took, start to end, over its
    FINISHED runs at the latest scale. A run copied from another table (tag ``reused_from``, :func:`ablate.jobs.reuse.reuse`)
    took seconds to copy: the time of the run it was copied from counts (read from ``tracker``). The racing sweeper
    weighs its estimate of a look's wall time with these (``hydra_plugins/ablate_racing_sweeper``): rows of one
    table can differ twofold in their cost."""
    runs = at_latest_scale(runs)
    if not len(runs):
        return {}
    seconds = ((runs["ended"] - runs["started"]) / 1000.0).astype(float)
    for i, source in runs["reused_from"].items():
        if source:
            try:
                run = tracker.get_run(source)
                seconds[i] = ((run.info.end_time or run.info.start_time) - run.info.start_time) / 1000.0
            except MlflowException:  # the source is gone from this store (not found): its time is unknown
                seconds[i] = float("nan")
    medians = seconds.groupby(runs["row"]).median().dropna()
    return {str(row): float(value) for row, value in medians.items()}


def sweep_wall(began: pd.Series, ended: pd.Series, sweep: pd.Series | None) -> tuple[float, int]:
    """Wall time in minutes and over how many sweeps: per sweep (the same command run again after a stop is a
    sweep of its own), its first start to its last end, added up, never the time between sweeps. Epoch
    milliseconds in; rows without a sweep (older records) are one span."""
    sweep = pd.Series("", index=began.index) if sweep is None else sweep.fillna("").astype(str)
    spans = pd.DataFrame({"sweep": sweep, "first": began, "last": ended}).groupby("sweep")
    return float((spans["last"].max() - spans["first"].min()).sum()) / 60000, int(spans.ngroups)


def earlier_wall(runs: pd.DataFrame | None, sweep_id: str | None) -> float:
    """Minutes of wall time that sweeps other than ``sweep_id`` spent on the latest runs (:func:`latest`: the very
    runs the table and its race use), per sweep as the footer counts it (:func:`sweep_wall`): what a race resumed
    by the same command had spent before it, to be counted against its budget."""
    if runs is None or not len(runs):
        return 0.0
    runs = latest(runs)
    sweeps = runs["sweep_id"].fillna("").astype(str) if "sweep_id" in runs else pd.Series("", index=runs.index)
    other = runs[sweeps != (sweep_id or "")]
    if not len(other):
        return 0.0
    began = other["job_started"].fillna(other["started"]) if "job_started" in other else other["started"]
    return sweep_wall(began, other["ended"], other.get("sweep_id"))[0]


def made_lines(runs: pd.DataFrame) -> list[str]:
    """The footer's line on how the rows were made: the CPU (and the GPU, where runs trained on one), precision and
    threads of the runs (each set with its run count where they differ: the numerics are a source of variation of
    their own), and the wall time: per
    sweep the runs came from, its first job's start to its last job's end, added up (from the runs alone, so the
    same runs give the same line), beside the jobs' own time added up. A job starts where it began training or
    waiting for its experts (``job_started``), before its run; records without that column start at the run."""
    if not len(runs) or "made_cpu" not in runs:
        return []
    gpus = runs["made_gpu"].fillna("") if "made_gpu" in runs else pd.Series("", index=runs.index)
    kinds = runs.assign(made_gpu=gpus).groupby([f"made_{k}" for k in MADE] + ["made_gpu"]).size()
    made = [
        f"{cpu}{f' with {gpu}' if gpu else ''}, precision {precision}, {threads} thread(s) per job"
        + (f" ({n} runs)" if len(kinds) > 1 else "")
        for (cpu, precision, threads, gpu), n in kinds.items()
    ]
    began = runs["job_started"] if "job_started" in runs else runs["started"]
    wall, sweeps = sweep_wall(began, runs["ended"], runs.get("sweep_id"))
    head = "Made on " if len(kinds) == 1 else "**Mixed machines or numerics**: made on "
    return [
        f"{head}{'; '.join(made)}; wall time {wall:.0f} min over {sweeps} sweep(s), "
        f"{(runs['ended'] - began).sum() / 60000:.0f} min of job time."
    ]


def running(tracker: Tracker, table: str) -> int:
    """How many job runs of ``table`` are RUNNING (a sweep writing now, or a killed job not yet closed): never rows."""
    exp = tracker.find_experiment(table)
    if exp is None:
        return 0
    return len(tracker.runs(exp, f"attributes.status = 'RUNNING' and tags.kind = '{KIND_JOB}'"))


def resumed_step(tags: dict[str, str]) -> str:
    """The training step a run resumed from a checkpoint at (tag ``resumed_step``, :func:`ablate.jobs.checkpoint.
    resume_point`); "" for a run trained uninterrupted (from scratch, step 0, or without the tag)."""
    step = str(tags.get("resumed_step") or "")
    return "" if step in ("", "0") or tags.get("resumed_from") == "scratch" else step


def resumed_lines(runs: pd.DataFrame) -> list[str]:
    """The footer's line on the runs resumed from a checkpoint (``resumed_step``), or that the records predate
    the column."""
    if not len(runs):
        return []
    if "resumed_step" not in runs:
        return ["Resumed runs: not recorded (these records predate the `resumed_step` column)."]
    steps = runs["resumed_step"].fillna("").astype(str)
    resumed = runs[(steps != "") & (steps != "0")]
    if not len(resumed):
        return []
    named = ", ".join(
        f"{r} seed {s} at step {st}" for r, s, st in zip(resumed["row"], resumed["seed"], resumed["resumed_step"])
    )
    return [
        f"**Resumed runs**: {len(resumed)} of {len(runs)} resumed from a checkpoint ({named}); a run resumed before "
        "resuming restored the training order and generators (6d500ba) is not the computation an uninterrupted run is."
    ]


def loaded_runs(runs: pd.DataFrame) -> pd.Series:
    """Which of ``runs`` were loaded from an earlier store's published records (``loaded_from``), by run."""
    return runs[LOADED].fillna("").astype(str) != "" if LOADED in runs else pd.Series(False, index=runs.index)


def loaded_lines(runs: pd.DataFrame) -> list[str]:
    """The footer's line on the runs loaded from an earlier store's published records (``loaded_from``), where any
    were: they trained where and when their records say, not in the sweep that loaded them."""
    loaded = loaded_runs(runs)
    if not loaded.any():
        return []
    return [
        f"{int(loaded.sum())} of {len(runs)} runs were loaded from the published records of an earlier store "
        "(`python -m ablate.report --extend`) and raced on; each trained where and when its record says."
    ]


def state_lines(runs: pd.DataFrame, in_progress: int) -> list[str]:
    """The footer's lines on what the table leaves out: the RUNNING runs, and the bad frames the runs' data
    modules skipped (``data.on_bad_frame=skip``), where there are any."""
    lines = []
    if in_progress:
        lines.append(
            f"{in_progress} run(s) still RUNNING are left out (a sweep is writing, or a killed job not yet rerun); "
            "regenerate with `python -m ablate.report` when they end."
        )
    if len(runs) and SKIPPED_FRAMES in runs:
        skipped = runs[SKIPPED_FRAMES].fillna(0)
        if skipped.sum() > 0:
            lines.append(
                f"{int(skipped.sum())} bad frame(s) skipped (data.on_bad_frame=skip) in {int((skipped > 0).sum())} "
                "run(s); each run's log names them."
            )
    return lines


def under_condition(runs: pd.DataFrame, table: DictConfig) -> pd.DataFrame:
    """``runs`` with the metrics of ``table.primary_condition`` (``<condition>/<metric>``) as the plain metrics."""
    condition = table.get("primary_condition")
    if not condition or not len(runs):
        return runs
    prefix = f"{condition}/"
    moved = {c: c[len(prefix) :] for c in runs.columns if str(c).startswith(prefix)}
    return runs.drop(columns=[c for c in moved.values() if c in runs]).rename(columns=moved)
