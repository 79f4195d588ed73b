"""The runs of a table, from the store, as a pandas frame: one row per (table row, seed)."""

from __future__ import annotations

import pandas as pd
from omegaconf import DictConfig

from ablate.store import KIND_JOB, SKIPPED_FRAMES, Tracker, retry


def collect(tracker: Tracker, table: str) -> pd.DataFrame:
    """One row per (row, seed) of ``table``: its latest FINISHED job run, at the scale of the latest such run.

    A rerun after a config change (another recipe, another dataset) supersedes the earlier run of the same row and
    seed instead of counting as one more seed; runs at another scale (a smoke sweep beside the default-scale table)
    stay in the store and out of the table."""
    exp = retry(tracker.client.get_experiment_by_name, table)
    if exp is None:
        return pd.DataFrame()
    runs = tracker.runs(exp.experiment_id, f"attributes.status = 'FINISHED' and tags.kind = '{KIND_JOB}'")
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
            "start": r.info.start_time,
            **r.data.metrics,
        }
        for r in runs
    ]
    if not records:
        return pd.DataFrame()
    df = pd.DataFrame.from_records(records).sort_values(["start", "config_hash"], kind="stable")
    df = df[df["scale"] == df["scale"].iloc[-1]]
    return df.drop_duplicates(["row", "seed"], keep="last").drop(columns="start").reset_index(drop=True)


def running(tracker: Tracker, table: str) -> int:
    """How many job runs of ``table`` are RUNNING (a sweep writing now, or a killed job not yet closed): never rows."""
    exp = retry(tracker.client.get_experiment_by_name, table)
    if exp is None:
        return 0
    return len(tracker.runs(exp.experiment_id, f"attributes.status = 'RUNNING' and tags.kind = '{KIND_JOB}'"))


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
