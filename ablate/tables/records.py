"""A table's run records: the runs a published table uses, as a plain CSV beside it (``results/runs/<table>.csv``),
from which the report renders the table again on any machine, with no store (DomainBed's ``results.jsonl`` ->
``collect_results.py`` is the model: records in, tables out).

One line per run the table uses (:func:`ablate.tables.collect.collect`: per row and seed the latest FINISHED run,
at the latest scale): who it is (``table``, ``row``, ``seed``, ``status``, ``scale``, ``config_hash``), the code
that made it (``git_commit``, its ``fingerprint``, ``evaluator``, ``targets``), where and how (``made_cpu``,
``cpu_isa``, ``cpu_kernels``: the kernels torch ran, :func:`ablate.hardware.kernels`, absent from older records, ``made_gpu``: the GPU, empty on the CPU and absent from older records, ``made_precision``,
``made_threads``), when (``started``, ``ended`` in ms, ``seconds``, and
``job_started``, the job's start before its experts), the race and
sweep it belongs to (``race_plan``, ``sweep_id``, ``job_num``, ``reused_from``, ``run_id``), the training step it
resumed from a checkpoint at (``resumed_step``, empty for a run trained uninterrupted; absent from older records), the
record it was loaded from (``loaded_from``, :data:`LOADED`; only where a run was), the config a tuning
phase chose for its row (``tuned_config``, empty where the row was not tuned), and one column per
final metric: the test metrics the table shows (per condition and difficulty where it has them), latency and
costs. No per-step history, no checkpoints. Numbers are written as Python's shortest round-trip form, so a table
rendered from the records is the table rendered from the store, byte for byte. Each records file is sealed where it
is written (:mod:`ablate.tables.seal`), and checked against its seal before a table is rendered from it.
"""

from __future__ import annotations

from pathlib import Path

import pandas as pd

from ablate.store import Tracker
from ablate.tables.seal import Kind, check, reseal, write_csv

#: Where records live under a results folder.
RUNS_DIR = "runs"
#: The text columns of a record (a run's tags): read back as text, never as numbers.
TEXT = (
    "table",
    "row",
    "seed",
    "status",
    "scale",
    "config_hash",
    "git_commit",
    "run_id",
    "evaluator",
    "fingerprint",
    "targets",
    "made_cpu",
    "cpu_isa",
    "cpu_kernels",
    "made_gpu",
    "made_precision",
    "made_threads",
    "sweep_id",
    "race_plan",
    "tuned_config",
    "reused_from",
    "resumed_step",
    "loaded_from",
)
#: The tag (and record column) of a job's run loaded from a published record (``python -m ablate.report --extend``,
#: :mod:`ablate.analysis.extend`): ``<records file>#<recorded run id>``; absent from records without such runs.
LOADED = "loaded_from"
#: The whole-number columns: the job's number in its sweep, its run's start and end (ms since the epoch), and the
#: job's start before the experts it trained first (``job_started``; absent from records written before it).
WHOLE = ("job_num", "started", "ended", "job_started")
#: What a missing or empty text column reads as where records are compared: a run on the CPU names no GPU, and
#: records written before the column have none; any other column unknown reads ``?``.
ABSENT = {"made_gpu": "none", "cpu_kernels": "not recorded"}
#: Columns whose absence says nothing (older records): never a difference.
UNKNOWN_IF_ABSENT = ("cpu_kernels",)
#: Metrics a record leaves out: the per-epoch ones (their last values) and the test metrics' second names.
HISTORY = ("train/", "val/", "test/", "epoch", "lr")


def text_of(value: object, column: str) -> str:
    """``value`` of a record's text ``column`` as text, :data:`ABSENT`'s reading where it is missing or empty."""
    if value is None or (isinstance(value, float) and value != value) or value == "":
        return ABSENT.get(column, "?")
    return str(value)


#: The record columns that say how a number was computed, beside the config, and how a line names each.
NUMERICS = {
    "made_cpu": "CPU",
    "cpu_isa": "ISA",
    "cpu_kernels": "kernels",
    "made_gpu": "GPU",
    "made_precision": "precision",
    "made_threads": "threads",
}


def numerics_differ(before: pd.DataFrame, now: pd.DataFrame) -> list[str]:
    """``name: before's value(s) -> now's`` for each of :data:`NUMERICS` whose values differ between the runs
    ``before`` and ``now`` (rows of a table's runs or records; a missing column reads as :data:`ABSENT` says)."""
    out = []
    for column, name in NUMERICS.items():
        was, is_ = (sorted({text_of(v, column) for v in runs.get(column, pd.Series([None]))}) for runs in (before, now))
        if column in UNKNOWN_IF_ABSENT and ABSENT[column] in (*was, *is_):
            continue  # records made before the column: not known to differ
        if was != is_:
            out.append(f"{name}: {' / '.join(was)} -> {' / '.join(is_)}")
    return out


def records_path(results_dir: str | Path, table: str) -> Path:
    """The records of ``table`` under ``results_dir``: ``<results_dir>/runs/<table>.csv``."""
    return Path(results_dir) / RUNS_DIR / f"{table}.csv"


def to_records(runs: pd.DataFrame, table: str) -> pd.DataFrame:
    """The record of each of a table's runs (the frame :func:`~ablate.tables.collect.collect` gives), its columns
    in a fixed order: :data:`TEXT`, :data:`WHOLE`, ``seconds``, then the final metrics, sorted by name."""
    out = runs.copy()
    out["table"], out["status"] = table, "FINISHED"
    if "cpu_isa" not in out:
        out["cpu_isa"] = "?"
    out["seconds"] = ((out["ended"] - out["started"]) / 1000.0).astype(float)
    if LOADED in out and not out[LOADED].fillna("").astype(str).str.len().any():
        out = out.drop(columns=LOADED)  # no run loaded from records: the column is left out, as before it existed
    known = set(TEXT) | set(WHOLE) | {"seconds"}
    metrics = sorted(c for c in out.columns if c not in known and not str(c).startswith(HISTORY))
    return out[[c for c in (*TEXT, *WHOLE, "seconds") if c in out] + metrics]


def write_records(runs: pd.DataFrame, table: str, results_dir: str | Path) -> Path:
    """Write a table's records (:func:`to_records`) to :func:`records_path`, sealed
    (:func:`ablate.tables.seal.write_csv`); the path."""
    return write_csv(to_records(runs, table), records_path(results_dir, table))


#: The records files beside a table, each of its kind (:class:`ablate.tables.seal.Kind`): the runs (this module),
#: their learning curves (:mod:`~ablate.tables.curves`), tuning trials (:mod:`~ablate.tables.tuning`), counts and
#: detections per test frame (:mod:`~ablate.tables.frames`).
KINDS = (
    Kind(".csv", ("table", "row", "seed", "run_id"), ("run_id",), TEXT, WHOLE),
    Kind(
        ".curves.csv",
        ("run_id", "row", "seed", "metric", "epoch", "value"),
        ("run_id", "metric", "epoch"),
        ("run_id", "row", "seed", "metric"),
        ("epoch",),
    ),
    Kind(
        ".trials.csv",
        ("run_id", "row", "trial"),
        ("run_id",),
        ("run_id", "row", "seed", "status", "trial_config", "cpu", "search", "sweep_id"),
        ("trial", "started"),
    ),
    Kind(".frames.csv.gz", ("run_id", "row", "seed", "frame"), ("run_id", "frame", "condition")),
    Kind(".detections.csv.gz", ("run_id", "row", "seed", "frame", "metric")),
)


def check_records(results_dir: str | Path, table: str) -> None:
    """Raise :class:`~ablate.tables.seal.BrokenRecords` where a records file of ``table`` under ``results_dir`` is
    not what was written (:func:`ablate.tables.seal.check`)."""
    check(Path(results_dir) / RUNS_DIR, table, [k.suffix for k in KINDS])


def reseal_records(results_dir: str | Path, table: str) -> Path | None:
    """Seal ``table``'s records under ``results_dir`` again after an intended edit, once each file parses
    (:func:`ablate.tables.seal.reseal`); the seal, None where the table has no records."""
    return reseal(Path(results_dir) / RUNS_DIR, table, KINDS)


def read_records(path: str | Path) -> pd.DataFrame:
    """A table's runs from its records, in the frame the tables read from the store (:func:`to_records`' columns;
    text columns as text, metrics as floats, a missing metric NaN)."""
    path = Path(path)
    header = pd.read_csv(path, nrows=0).columns
    numeric = [c for c in header if c not in TEXT]
    frame = pd.read_csv(
        path,
        dtype={**{c: str for c in header if c in TEXT}, **{c: "int64" for c in header if c in WHOLE}},
        keep_default_na=False,
        na_values={c: [""] for c in numeric if c not in WHOLE},
    )
    for column in numeric:
        if column not in WHOLE:
            frame[column] = frame[column].astype(float)
    return frame


#: The tag an imported run carries: the record it was made from (``<records file>#<run id>``).
IMPORTED = "imported_from"
#: The kind of an imported run: never a job of this store, so no job skips on it and no table here counts it.
KIND_IMPORTED = "imported"
#: Record columns that become tags of another name (the rest of :data:`TEXT` keep theirs, but ``status``): the
#: config hash and run id are the recorded run's, kept apart from this store's own.
TAG_NAMES = {
    "made_cpu": "cpu",
    "made_gpu": "gpu",
    "made_precision": "precision",
    "made_threads": "threads",
    "config_hash": "recorded_config_hash",
    "run_id": "recorded_run_id",
}


def load_records(tracker: Tracker, path: Path) -> int:
    """Load a table's records into ``tracker``'s store as FINISHED runs of its experiment, of kind
    :data:`KIND_IMPORTED` and tagged :data:`IMPORTED` (the record they come from), with the recorded tags, final
    metrics and times, so that ``mlflow ui`` shows the runs behind a published table. They are not this store's
    jobs: none is skipped or reused on them, and no table rendered from this store counts them. A record already
    loaded is not loaded again; how many were."""
    records = read_records(path)
    if not len(records):
        return 0
    exp = tracker.experiment_id(str(records["table"].iloc[0]))
    done = {r.data.tags.get(IMPORTED) for r in tracker.runs(exp, f"tags.{IMPORTED} != ''")}
    loaded = 0
    for _, record in records.iterrows():
        origin = f"{path.as_posix()}#{record['run_id']}"
        if origin in done:
            continue
        shown = [c for c in TEXT if c != "status" and c in record and str(record[c]) != ""]
        tags = {TAG_NAMES.get(c, c): str(record[c]) for c in shown} | {"kind": KIND_IMPORTED, IMPORTED: origin}
        metrics = {c: float(record[c]) for c in records.columns if c not in (*TEXT, *WHOLE) and pd.notna(record[c])}
        name = f"{record['row']} seed={record['seed']} (imported)"
        tracker.import_run(exp, name, tags, metrics, int(record["started"]), int(record["ended"]))
        loaded += 1
    return loaded
