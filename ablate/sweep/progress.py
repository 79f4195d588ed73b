"""A sweep's overall progress: jobs finished of planned, and an ETA from the finished jobs' durations.

The racing sweeper records how many jobs its plan launches (``progress.planned`` in the sweep's state file,
:mod:`ablate.sweep.state`: the jobs of :meth:`ablate.sweep.launches.SweepPlan.jobs`, a race's first look; each later
look adds its own); every job, in whichever process runs it, adds its outcome and duration to the state's ``ended``
and logs one line such as
``Sweep progress: 4/9 jobs finished (1 skipped), 5 to go, ETA 11 min (2.2 min per trained job, 2 at a time)``.

A table's tuning phase runs jobs of other kinds than its raced ones (:func:`job_kind`): an expert's tuning trial trains
a single-modal network, a row's trial trains without testing, a raced job trains and tests under every condition. The
sweep records how many of each kind it plans (``kinds``) and, once its plan is estimated, each kind's estimated
seconds per job (``estimates``, :mod:`ablate.sweep.plan`); the ETA times every kind's jobs to go at its own finished
jobs' mean, a kind none of whose jobs has finished yet at its plan's estimate scaled by how the finished jobs compared
with theirs (up to their size; a larger job's rest at the plan's pace: :func:`_scale`), and schedules them on the
sweep's workers in launch order.

A tuning phase launches trial k of every row at once and waits for them all before trial k + 1
(:mod:`ablate.sweep.tuning`), so a trial index takes as long as its slowest row. The sweep records each tuned kind's
rows (``launches``) and every job its row and trial number; the ETA then schedules the trials to go launch by launch,
each trial at its own row's mean where that row has finished one, and the raced jobs after the last launch.

A raced job on experts (SMoE §4.3) trains whichever of them is missing first, within the job
(:mod:`ablate.jobs.stage1`), so the first jobs of a look take an expert's training more than the rest. The sweep
records how many experts of each modality its looks will train and the plan's estimate of one of each (``experts``);
every job records the seconds of each expert it trained, by modality, and its seconds in stage 1. The ETA times each
job to go at the jobs' mean less their stage 1, and each expert to go, before them, at the trained experts' mean of its
modality (a camera expert can take three times a BEV one), else at its estimate scaled as the trained experts of the
other modalities came out against theirs, else as a kind's.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from ablate.sweep import state

#: The kinds of a sweep's jobs in launch order (:func:`job_kind`), and how a progress line names one of each.
KINDS = {"expert trial": "expert trial", "trial": "tuning trial", "job": "trained job"}


def _values(overrides: list[str]) -> dict[str, str]:
    return {key.lstrip("+~"): value for key, _, value in (item.partition("=") for item in overrides)}


def job_kind(overrides: list[str]) -> str:
    """The kind of the job of ``overrides``: ``expert trial`` (an expert's tuning trial, ``experts.tune``),
    ``trial`` (a row's tuning trial, ``trial``), else ``job`` (a raced or swept job)."""
    keys = _values(overrides)
    return "expert trial" if "experts.tune" in keys else "trial" if "trial" in keys else "job"


def job_row(overrides: list[str]) -> str:
    """The row of the job of ``overrides`` as its tuning launches name it: ``expert <modality>`` for an expert's
    trial, else its ``row`` ("" where it has none)."""
    values = _values(overrides)
    return f"expert {values['experts.tune']}" if "experts.tune" in values else values.get("row", "")


def job_trial(overrides: list[str]) -> int | None:
    """The trial number of the job of ``overrides`` (None: no tuning trial)."""
    values = _values(overrides)
    return int(values["trial"]) if values.get("trial", "").isdigit() else None


def start(sweep_dir: Path, jobs: list[list[str]]) -> int:
    """Record the planned jobs of the sweep in ``sweep_dir`` (``jobs``, :meth:`ablate.sweep.launches.SweepPlan.jobs`):
    their count, each kind's but ``job`` (whose count a race's later looks change, :func:`replan`) and the rows each
    of its launches holds; return the count."""
    kinds = Counter(job_kind(job) for job in jobs)
    launches: dict[str, list[str]] = {}
    for kind, row in ((job_kind(job), job_row(job)) for job in jobs):
        if row not in (rows := launches.setdefault(kind, [])):
            rows.append(row)
    planned = {
        "planned": len(jobs),
        "kinds": {k: n for k, n in kinds.items() if k != "job"},
        "launches": {k: rows for k, rows in launches.items() if k != "job"},
    }
    state.record(sweep_dir, progress=planned, ended=[])
    return len(jobs)


def _progress(sweep_dir: Path, values: Mapping[str, Any]) -> None:
    """Set ``values`` in the state's ``progress``."""
    state.change(sweep_dir, lambda now: now.setdefault("progress", {}).update(values))


def replan(sweep_dir: Path, planned: int) -> None:
    """Record a new planned job count (a race's next look adds jobs)."""
    _progress(sweep_dir, {"planned": planned})


def experts_planned(sweep_dir: Path, count: Mapping[str, int], seconds: Mapping[str, float] | None = None) -> None:
    """Add ``count`` experts of each modality to those the sweep's jobs will train within them (a race's first look,
    then each later look's), with the plan's estimated ``seconds`` of one of each modality where it has them."""

    def add(now: dict[str, Any]) -> None:
        known = now.setdefault("progress", {}).setdefault("experts", {})
        each = _modalities(known)
        for modality, n in count.items():
            each.setdefault(modality, {"planned": 0})["planned"] += int(n)
        for modality, sec in (seconds or {}).items():
            if sec:
                each.setdefault(modality, {"planned": 0})["seconds"] = round(float(sec), 3)
        known.clear()
        known.update(planned=sum(e["planned"] for e in each.values()), modalities=each)

    state.change(sweep_dir, add)


def _modalities(experts: Mapping[str, Any]) -> dict[str, dict[str, float]]:
    """The planned experts of each modality, ``{modality: {"planned": n, "seconds": s}}``, from the sweep's record of
    them (one written before experts were counted by modality: all under ``""``)."""
    if "modalities" in experts:
        return {m: dict(e) for m, e in experts["modalities"].items()}
    if not experts.get("planned"):
        return {}
    old: dict[str, float] = {"planned": int(experts["planned"])}
    return {"": {**old, "seconds": float(experts["seconds"])} if experts.get("seconds") else old}


def _trained(records: list[dict]) -> list[tuple[str, float]]:
    """The experts the finished jobs trained: (modality, seconds) each (a record of a list: modality ``""``)."""
    out: list[tuple[str, float]] = []
    for r in records:
        experts = r.get("experts") or {}
        pairs = experts.items() if isinstance(experts, Mapping) else (("", s) for s in experts)
        out += [(str(m), float(s)) for m, s in pairs]
    return out


def estimated(sweep_dir: Path, seconds: Mapping[str, float], rows: Mapping[str, Sequence[float]] | None = None) -> None:
    """Record the plan's estimated seconds per job of each kind, and its raced jobs of each row with their estimated
    seconds (``{row: [jobs, seconds]}``, :func:`ablate.sweep.plan.row_jobs`)."""
    known = {k: round(s, 3) for k, s in seconds.items()}
    each = {row: [int(n), round(float(sec), 3)] for row, (n, sec) in (rows or {}).items()}
    _progress(sweep_dir, {"estimates": known, "rows": each})


def finished(
    sweep_dir: Path,
    status: str,
    seconds: float,
    parallel: int = 1,
    kind: str = "job",
    row: str = "",
    trial: int | None = None,
    experts: Mapping[str, float] | None = None,
    stage1: float = 0.0,
) -> str:
    """Record one job's end (``status``: FINISHED, SKIPPED, FAILED; its wall ``seconds``; its ``kind``,
    :func:`job_kind`; its ``row`` and ``trial``, :func:`job_row`, :func:`job_trial`; the seconds of each of the
    ``experts`` it trained, by modality, and its seconds in ``stage1`` in all, :mod:`ablate.jobs.stage1`) and return
    the sweep's progress line."""
    record: dict[str, Any] = {"status": status, "seconds": round(seconds, 3), "kind": kind, "row": row, "trial": trial}
    if stage1:
        record.update(experts={m: round(e, 3) for m, e in (experts or {}).items()}, stage1=round(stage1, 3))

    def add(now: dict[str, Any]) -> dict[str, Any]:
        now.setdefault("ended", []).append(record)
        return now

    now = state.change(sweep_dir, add)
    planned = now.get("progress", {})
    records = now["ended"]
    return summary(
        records,
        int(planned.get("planned", len(records))),
        parallel,
        planned.get("kinds"),
        planned.get("estimates"),
        planned.get("launches"),
        planned.get("experts"),
        planned.get("rows"),
    )


def summary(
    records: list[dict],
    planned: int,
    parallel: int = 1,
    kinds: Mapping[str, int] | None = None,
    estimates: Mapping[str, float] | None = None,
    launches: Mapping[str, list[str]] | None = None,
    experts: Mapping[str, float] | None = None,
    rows: Mapping[str, Sequence[float]] | None = None,
) -> str:
    """The progress line for the finished jobs' ``records`` of ``planned``, ``parallel`` jobs at a time (``kinds``:
    the planned count of each kind but ``job``; ``estimates``: the plan's seconds per job of each kind; ``launches``:
    the rows of each tuned kind's launches; ``experts``: the experts the jobs will train, as :func:`experts_planned`
    records them; ``rows``: the plan's raced jobs of each row and their estimated seconds). The ETA takes each kind's
    trained jobs' mean duration less their stage 1 for its jobs to go (a skipped job costs nothing, but which
    of the rest will be skipped is not known; a kind without a trained job: see the module), scheduled on the
    workers in launch order, a tuning trial at its row's mean, a raced job at its row's where the plan names its
    rows (:func:`_raced`), the experts to go before the raced jobs (:func:`_wall`)."""
    done = len(records)
    skipped = sum(r["status"] == "SKIPPED" for r in records)
    failed = sum(r["status"] == "FAILED" for r in records)
    notes = ", ".join(f"{n} {word}" for n, word in ((skipped, "skipped"), (failed, "failed")) if n)
    line = f"Sweep progress: {done}/{planned} jobs finished" + (f" ({notes})" if notes else "")
    left = max(planned - done, 0)
    per = _per_job(records, estimates or {}, rows or {})
    if not left:
        return line
    to_go = _left(records, planned, kinds or {})
    if not all(kind in per for kind in to_go):
        return line + f", {left} to go"
    expert = _expert(records, experts or {}, estimates or {}, rows or {}) if to_go.get("job") else None
    raced = _raced(records, to_go.get("job", 0), per, estimates or {}, rows or {}) if "job" in per else []
    said = ", ".join(f"{_minutes(per[k][0])} per {KINDS[k]}{per[k][1]}" for k in KINDS if to_go.get(k) and k != "job")
    if expert is not None:
        low, high = _minutes(min(expert[0])), _minutes(max(expert[0]))
        at = low + (f" to {high}" if high != low else "")
        said += (", " if said else "") + f"{len(expert[0])} expert(s) to train at {at}{expert[1]}"
    if to_go.get("job") and rows:
        low, high = _minutes(min(raced)), _minutes(max(raced))
        said += (
            (", " if said else "") + f"{KINDS['job']}s at their rows' {low}" + (f" to {high}" if high != low else "")
        )
    elif to_go.get("job"):
        said += (", " if said else "") + f"{_minutes(per['job'][0])} per {KINDS['job']}{per['job'][1]}"
    workers = max(parallel, 1)
    wall = _wall(records, to_go, per, kinds or {}, launches or {}, workers, expert, raced)
    return line + f", {left} to go, ETA {_minutes(wall)} ({said}, {workers} at a time)"


def _wall(
    records: list[dict],
    to_go: Mapping[str, int],
    per: Mapping[str, tuple[float, str]],
    kinds: Mapping[str, int],
    launches: Mapping[str, list[str]],
    workers: int,
    expert: tuple[list[float], str] | None = None,
    raced: Sequence[float] = (),
) -> float:
    """The wall time of the jobs to go, kind after kind in launch order. A tuned kind whose launches are known
    (``launches``: its rows; ``kinds``: its planned count, the rows times the trials) runs trial k of its rows to go
    as one launch after another, each trial at its row's trained trials' mean (else its kind's); where the records
    do not account for its jobs to go (records without their rows), its jobs are packed as the raced jobs are; the
    ``expert`` s to go (the seconds of each) go before the raced jobs, each of those at its ``raced``
    seconds where given."""
    total = 0.0
    for kind in KINDS:
        rows, n = launches.get(kind) or [], to_go.get(kind, 0)
        if not n:
            continue
        ended = {(r.get("trial"), r.get("row")) for r in records if r.get("kind", "job") == kind}
        trials = kinds.get(kind, 0) // len(rows) if rows else 0
        rounds = [[row for row in rows if (k, row) not in ended] for k in range(trials)]
        if kind == "job" or sum(map(len, rounds)) != n:
            first = list(expert[0]) if kind == "job" and expert is not None else []
            jobs = list(raced) if kind == "job" and len(raced) == n else [per[kind][0]] * n
            total += schedule([*first, *jobs], workers)
            continue
        mean = _per_row(records, kind)
        total += sum(schedule([mean.get(row, per[kind][0]) for row in left], workers) for left in rounds)
    return total


def _per_row(records: list[dict], kind: str) -> dict[str, float]:
    """Each row's mean seconds over its trained jobs of ``kind``."""
    seconds: dict[str, list[float]] = {}
    for r in records:
        if r.get("kind", "job") == kind and r["status"] != "SKIPPED" and r.get("row"):
            seconds.setdefault(r["row"], []).append(_own(r))
    return {row: sum(s) / len(s) for row, s in seconds.items()}


def _left(records: list[dict], planned: int, kinds: Mapping[str, int]) -> dict[str, int]:
    """Each kind's jobs to go: its planned count (``job``: the rest of ``planned``) less its finished jobs."""
    ended = Counter(r.get("kind", "job") for r in records)
    counts = {**kinds, "job": planned - sum(kinds.values())}
    return {kind: n - ended[kind] for kind, n in counts.items() if n - ended[kind] > 0}


def _raced(
    records: list[dict],
    n: int,
    per: Mapping[str, tuple[float, str]],
    estimates: Mapping[str, float],
    rows: Mapping[str, Sequence[float]],
) -> list[float]:
    """The seconds of each of the ``n`` raced jobs to go: per row of the plan (``rows``), its jobs not yet ended, each
    at the row's trained jobs' mean less their stage 1, else at its estimate scaled as :func:`_per_job` scales a
    kind's; the jobs the plan did not name (a race's later looks) at the raced jobs' mean."""
    ended = Counter(r.get("row", "") for r in records if r.get("kind", "job") == "job")
    own, scale = _per_row(records, "job"), _scale(records, estimates, rows)
    seconds = [
        own.get(row, float(estimate) if scale is None else scale(float(estimate)))
        for row, (jobs, estimate) in rows.items()
        for _ in range(max(int(jobs) - ended[row], 0))
    ][:n]
    return seconds + [per["job"][0]] * (n - len(seconds))


def _per_job(
    records: list[dict], estimates: Mapping[str, float], rows: Mapping[str, Sequence[float]] | None = None
) -> dict[str, tuple[float, str]]:
    """Each kind's seconds per job and how they were had: its trained jobs' mean (""), else its estimate scaled by
    the trained jobs' durations over their kinds' estimates (" as planned"), else every trained job's mean."""
    seconds: dict[str, list[float]] = {}
    for r in records:
        if r["status"] != "SKIPPED":
            seconds.setdefault(r.get("kind", "job"), []).append(_own(r))
    if not seconds:
        return {}
    per = {kind: (sum(s) / len(s), "") for kind, s in seconds.items()}
    scale = _scale(records, estimates, rows)
    everything = [s for values in seconds.values() for s in values]
    for kind in KINDS:
        if kind not in per:
            guess = scale(estimates.get(kind, 0.0)) if scale is not None else 0.0
            per[kind] = (guess, " as planned") if guess > 0 else (sum(everything) / len(everything), "")
    return per


def _scale(
    records: list[dict], estimates: Mapping[str, float], rows: Mapping[str, Sequence[float]] | None = None
) -> Callable[[float], float] | None:
    """How a planned estimate comes out in seconds, from the trained jobs the plan estimated (None: no such job yet;
    a raced job's estimate its row's where the plan gives ``rows``, else its kind's). Their seconds (less their stage
    1) over their estimates' is the ratio ``r``; up to the largest of their estimates ``L`` an estimate ``e`` takes
    ``r e``, and beyond it, where the jobs came out slower than planned, ``r L + (e - L)``: the part of a job larger
    than any that ended at the plan's own pace. The plan times a job's steps, not its fixed costs (its start, its
    checkpoints, the test's data), so the first jobs to end, often a single-modal row that only tests its expert
    (9 s of steps planned, 17 s taken), are mostly fixed cost: their ratio, 1.9, once scaled a fused row's 1.8 min
    of steps to 3.4 min where it took 2.3."""

    def estimate(r: Mapping) -> float:
        row = (rows or {}).get(r.get("row", "")) if r.get("kind", "job") == "job" else None
        return float(row[1]) if row and row[1] else float(estimates.get(r.get("kind", "job"), 0.0))

    timed = [(estimate(r), _own(r)) for r in records if r["status"] != "SKIPPED" and estimate(r) > 0]
    if not timed:
        return None
    ratio, largest = sum(s for _, s in timed) / sum(e for e, _ in timed), max(e for e, _ in timed)
    if ratio <= 1:
        return lambda e: ratio * e
    return lambda e: ratio * min(e, largest) + max(e - largest, 0.0)


def _own(record: Mapping) -> float:
    """A finished job's seconds less its stage 1 (its experts: timed apart, :func:`_expert`)."""
    return max(float(record["seconds"]) - float(record.get("stage1", 0.0)), 0.0)


def _expert(
    records: list[dict],
    experts: Mapping[str, Any],
    estimates: Mapping[str, float],
    rows: Mapping[str, Sequence[float]] | None = None,
) -> tuple[list[float], str] | None:
    """The seconds of each expert to go (each modality's planned less trained, ``experts`` as
    :func:`experts_planned` records them) and how they were had: the trained experts' mean of its modality (""),
    else the plan's estimate of it scaled by the trained experts' seconds over their modalities' estimates, else
    scaled as :func:`_per_job` scales a kind's, else the trained experts' mean (" as planned" where no modality to
    go has trained one); None where none is to go or nothing times one."""
    trained, planned = _trained(records), _modalities(experts)
    own: dict[str, list[float]] = {}
    for modality, sec in trained:
        own.setdefault(modality, []).append(sec)
    timed = [(m, s) for m, s in trained if planned.get(m, {}).get("seconds")]
    ratio = sum(s for _, s in timed) / sum(float(planned[m]["seconds"]) for m, _ in timed) if timed else None
    scale = (lambda e: ratio * e) if ratio is not None else _scale(records, estimates, rows)
    everything = [s for _, s in trained]
    seconds: list[float] = []
    planned_only = True  # every expert to go timed from the plan's estimates
    for modality, each in planned.items():
        left = int(each.get("planned", 0)) - len(own.get(modality, ()))
        if left <= 0:
            continue
        if modality in own:
            sec, planned_only = sum(own[modality]) / len(own[modality]), False
        elif each.get("seconds"):
            sec = float(each["seconds"]) if scale is None else scale(float(each["seconds"]))
        elif everything:
            sec, planned_only = sum(everything) / len(everything), False
        else:
            continue
        seconds += [sec] * left if sec > 0 else []
    return (seconds, " as planned" if planned_only else "") if seconds else None


def look_seconds(sweep_dir: Path, jobs: int, experts: Mapping[str, int], parallel: int) -> float | None:
    """The wall time of a race's next look of ``jobs`` raced jobs that train ``experts`` experts of each modality
    within them (SMoE §4.3: the new seeds' experts, :mod:`ablate.jobs.stage1`), ``parallel`` at a time, timed as the
    ETA times the jobs to go (:func:`summary`): each expert at the trained experts' mean of its modality (else the
    plan's estimate, scaled), before the jobs, each at the trained jobs' mean less their stage 1. None where no job of
    the sweep has trained yet. The racing sweeper weighs a look's cost with it, beside its rows' costs
    (``hydra_plugins/ablate_racing_sweeper``): a look that races fewer rows than the first trains as many experts per
    seed."""
    now = state.read(sweep_dir)
    records, planned = now.get("ended", []), now.get("progress", {})
    estimates, rows = planned.get("estimates", {}), planned.get("rows", {})
    per = _per_job([r for r in records if r.get("kind", "job") == "job"], {})
    if "job" not in per:
        return None
    trained = Counter(m for m, _ in _trained(records))
    # the experts trained so far, then the look's: each modality's planned estimate kept
    look = {m: {**e, "planned": trained[m]} for m, e in _modalities(planned.get("experts", {})).items()}
    for modality, n in experts.items():
        look.setdefault(modality, {"planned": trained[modality]})["planned"] += int(n)
    expert = _expert(records, {"modalities": look}, estimates, rows)
    first = list(expert[0]) if expert is not None else []
    return schedule([*first, *[per["job"][0]] * jobs], parallel)


def workers(config: DictConfig) -> int:
    """How many jobs of the sweep of ``config`` run at once: the joblib launcher's ``n_jobs``, else 1."""
    n_jobs = OmegaConf.select(config, "hydra.launcher.n_jobs", default=None)
    return int(n_jobs) if isinstance(n_jobs, int) and n_jobs > 0 else 1


def schedule(seconds: list[float], parallel: int) -> float:
    """The wall time of jobs of ``seconds``, in order, on ``parallel`` workers, each job on the worker free first."""
    free = [0.0] * max(parallel, 1)
    for s in seconds:
        free[free.index(min(free))] += s
    return max(free)


def _minutes(seconds: float) -> str:
    return f"{seconds:.0f} s" if seconds < 90 else f"{seconds / 60:.1f} min"
