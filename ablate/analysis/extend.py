"""``python -m ablate.report --extend experiment=<table>``: a raced table's published records back in a store as its
own FINISHED jobs, so that ``python -m ablate -m experiment=<table>`` races on from its next look and trains only the
seeds the records lack.

A store does not outlive its machine, but a table's records do (``results/runs/``). A race stopped by its wall-time
budget, or asked for later looks (``scale.race.looks``), would otherwise train every recorded seed again before its
next look. A record stands in for its job only where the job would make the same numbers here
(:func:`refusal`):

* its config composed today (:func:`ablate.analysis.reproduce.recorded_config`) has the recorded config hash;
* it was made on this machine's kind: the same CPU model, instruction set, kernels (where recorded) and no GPU or
  the same GPU; precision and threads are in the hash (results follow the kernels and threads, ``docs/recipes.md``);
* the code it builds gives its numbers today: unchanged since its commit, or its recorded fingerprint recomputed
  today (:func:`ablate.tables.provenance.fingerprint_check`), and the evaluator its metrics were scored with is
  today's (:func:`ablate.tables.provenance.metric_changed`).

A record that fails one is named with the reason and not loaded; its job trains when the race comes to it. A loaded
run carries the recorded tags (its commit, sweep, times, numerics), final metrics, learning curves (the records'
per-epoch values, at step = epoch) and per-frame counts or detections (the artifacts a race's verdicts resample),
its params and config (``config.yaml``) composed today, and ``loaded_from`` (``<records file>#<run id>``, or the record's own where it was loaded
itself), which its table's records keep and whose footer counts. Its sweep and times are the recorded
ones, so the table's wall time and its race's budget count the earlier sweep: a race stopped by its budget goes on
only with a larger ``scale.race.budget_min``, given on the command line.

Not loaded: a table whose records hold a tuning phase (``runs/<table>.trials.csv``) or runs tuned by one: a store
cannot take a tuning phase back from its records (its trials' checkpoints are gone), so such a table is raced again
from the start. A record already in the store (a FINISHED job of its config hash, or loaded before) is left as it is.
"""

from __future__ import annotations

import tempfile
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import pandas as pd
from omegaconf import DictConfig, OmegaConf

from ablate import hardware
from ablate.analysis.reproduce import recorded_config
from ablate.jobs.spec import resolved_config
from ablate.jobs.tags import params_of
from ablate.jobs.train import DETECTION_COLUMNS
from ablate.store import FRAME_COUNTS, FRAME_DETECTIONS, KIND_JOB, Tracker, config_hash
from ablate.tables.curves import COLUMNS as CURVE_COLUMNS
from ablate.tables.curves import curves_path, read_curves
from ablate.tables.frames import read_detections, read_frames
from ablate.tables.provenance import Recompute, fingerprint_check, metric_changed, stale
from ablate.tables.records import LOADED, NUMERICS, TEXT, WHOLE, numerics_differ, read_records, records_path, text_of
from ablate.tables.tuning import trials_path

#: Record columns that are tags of another name on a job's run (the rest of :data:`TAGS` keep theirs).
TAG_NAMES = {"made_cpu": "cpu", "made_precision": "precision", "made_threads": "threads", "made_gpu": "gpu"}
#: Record columns that are no tag of a loaded job's run: what the store gives it (status, run id, times), its
#: targets (from its params), and the record it came from (the tag :data:`LOADED`, set apart); a run copied from
#: another table (``reused_from``) is loaded as the table's own, its artifacts with it.
NOT_TAGS = ("status", "run_id", "targets", "reused_from", LOADED, "started", "ended")
#: Record columns a loaded job's run carries as tags (those :func:`ablate.tables.collect.job_runs` reads back).
TAGS = tuple(c for c in (*TEXT, *WHOLE) if c not in NOT_TAGS)


@dataclass
class Extended:
    """What :func:`extend_table` did: the runs loaded, those the store already held, and each record refused with
    why (``row seed N: reason``)."""

    loaded: int = 0
    held: int = 0
    refused: list[str] = field(default_factory=list)


def machine_differs(record: pd.Series, mine: dict[str, str]) -> str | None:
    """How the machine and numerics that made ``record`` differ from this machine's tags ``mine``
    (:func:`ablate.tables.records.numerics_differ`: ``CPU: recorded -> here``), or None."""
    here = pd.DataFrame([{c: mine.get(TAG_NAMES.get(c, c)) for c in NUMERICS}])
    out = numerics_differ(record.to_frame().T, here)
    return "made on other numerics than this machine's (" + "; ".join(out) + ")" if out else None


def code_refusals(records: pd.DataFrame, recompute: Recompute, config: Callable[[str], DictConfig]) -> dict[str, str]:
    """{row: why today's code may not give its records' numbers}: code the row builds changed since its commit and
    its recomputed fingerprint differs (or it has none), or its metrics were scored by another evaluator."""
    out: dict[str, str] = {}
    targets = set(" ".join(records["targets"].fillna("")).split()) if "targets" in records else set()
    commit = records["git_commit"].fillna("unknown").str.removesuffix("-dirty")
    changed = stale(set(commit) - {"unknown"}, targets) if targets else {}
    for sha, files in changed.items():
        sel = records[commit == sha]
        has = sel["fingerprint"].fillna("") != ""
        for row, reason in fingerprint_check(sel[has], recompute, config).items():
            if reason is not None:
                out[row] = reason
        for row in sorted(set(sel.loc[~has, "row"])):
            out.setdefault(str(row), f"code it builds changed since {sha[:12]} ({files[0]}) and it has no fingerprint")
    for row in sorted(set(records.loc[commit == "unknown", "row"])):
        out.setdefault(str(row), "made by an ablate of unknown commit")
    for row, sel in records.groupby("row", sort=True):
        if lines := metric_changed(sel, targets):
            out.setdefault(str(row), lines[0].split(": ", 1)[1].split(";")[0])
    return out


def refusal(record: pd.Series, resolved: DictConfig) -> str | None:
    """Why ``record`` cannot stand in for its job here (its config hash today, its machine), or None; ``resolved``:
    its config composed today, resolved for this machine (:func:`ablate.jobs.spec.resolved_config`)."""
    today = config_hash(resolved)
    if today != str(record["config_hash"]):
        return f"its config today has config hash {today}, the record {record['config_hash']}"
    return machine_differs(record, hardware.tags(resolved))


def extend_table(tracker: Tracker, name: str, results: Path, recompute: Recompute, base: list[str]) -> Extended:
    """Load ``name``'s records under ``results`` into ``tracker``'s store as its own FINISHED jobs where they stand
    in for them (:func:`refusal`, :func:`code_refusals`); ``base``: overrides the records' configs compose on
    (``experiment=<name>`` and the command's own). A table with a tuning phase is one ValueError."""
    path = records_path(results, name)
    records = read_records(path)
    tuned = records.get("tuned_config", pd.Series(dtype=str)).fillna("").astype(str)
    if trials_path(results, name).exists() or (tuned != "").any():
        raise ValueError(
            f"{name}'s records hold a tuning phase ({trials_path(results, name)}), which a store cannot take back "
            "from records: race the table again from the start"
        )
    config = recorded_config(records, base)
    by_code = code_refusals(records, recompute, config)
    exp = tracker.experiment_id(name)
    loaded = {r.data.tags.get(LOADED) for r in tracker.runs(exp, f"tags.{LOADED} != ''")}
    curves = read_curves(curves_path(results, name)) if curves_path(results, name).exists() else None
    frames, detections = read_frames(results, name), read_detections(results, name)
    out = Extended()
    for _, record in records.iterrows():
        # a run loaded before it was published keeps the record it first came from
        origin = str(record.get(LOADED) or "") or f"{path.as_posix()}#{record['run_id']}"
        if origin in loaded or tracker.finished_run(exp, str(record["config_hash"])) is not None:
            out.held += 1
            continue
        resolved = resolved_config(config(str(record["run_id"])))[0]
        reason = by_code.get(str(record["row"])) or refusal(record, resolved)
        if reason is not None:
            out.refused.append(f"{record['row']} seed {record['seed']}: {reason}")
            continue
        run_id = load_job(tracker, exp, record, origin, params_of(resolved))
        tracker.log_text(run_id, OmegaConf.to_yaml(resolved, resolve=True), "config.yaml")  # as a job logs it
        log_curves(tracker, run_id, record, curves)
        log_frames(tracker, run_id, str(record["run_id"]), frames, detections)
        tracker.end_at(run_id, "FINISHED", int(record["ended"]))
        out.loaded += 1
    return out


def load_job(tracker: Tracker, exp: str, record: pd.Series, origin: str, params: dict[str, str]) -> str:
    """A job's run of ``record`` in experiment ``exp``, RUNNING until its history and artifacts are in: its recorded
    tags, params and final metrics, started when the record started."""
    shown = {c: text_of(record.get(c), c) for c in TAGS if c in record and str(record.get(c, "")) not in ("", "nan")}
    tags = {TAG_NAMES.get(c, c): v for c, v in shown.items()} | {"kind": KIND_JOB, LOADED: origin}
    tags["mlflow.source.git.commit"] = str(record.get("git_commit", ""))
    metrics = {c: float(record[c]) for c in record.index if c not in (*TEXT, *WHOLE, "seconds") and pd.notna(record[c])}
    run_id = tracker.start_at(exp, f"{record['row']} seed={record['seed']}", tags, int(record["started"]))
    tracker.log_params(run_id, params)
    tracker.log_rows(run_id, [(k, v, int(record["ended"]), 0) for k, v in sorted(metrics.items())])
    return run_id


def log_curves(tracker: Tracker, run_id: str, record: pd.Series, curves: pd.DataFrame | None) -> None:
    """The record's learning curves (``runs/<table>.curves.csv``: per epoch) as metric histories at step = epoch,
    which :func:`ablate.tables.curves.from_store` reads back as the same epochs and values."""
    if curves is None:
        return
    mine = curves[curves["run_id"] == str(record["run_id"])]
    when = int(record["ended"])
    tracker.log_rows(run_id, [(m, float(v), when, int(e)) for m, e, v in mine[CURVE_COLUMNS[3:]].itertuples(False)])


def log_frames(tracker: Tracker, run_id: str, recorded: str, frames: pd.DataFrame, detections: pd.DataFrame) -> None:
    """The recorded run's counts or detections per test frame as the loaded run's artifacts
    (:data:`ablate.store.FRAME_COUNTS`, :data:`ablate.store.FRAME_DETECTIONS`), as a job logs them."""
    ids = ["run_id", "row", "seed"]
    for kept, artifact in ((frames, FRAME_COUNTS), (detections, FRAME_DETECTIONS)):
        if kept.empty:
            continue
        mine = kept[kept["run_id"] == recorded].drop(columns=ids)
        if mine.empty:
            continue
        if artifact == FRAME_DETECTIONS:
            mine = mine[list(DETECTION_COLUMNS)]
        with tempfile.TemporaryDirectory() as folder:
            target = Path(folder) / Path(artifact).name
            gz = {"method": "gzip", "mtime": 0} if target.suffix == ".gz" else None
            mine.to_csv(target, index=False, compression=gz)
            tracker.log_artifact(run_id, target, str(Path(artifact).parent))
