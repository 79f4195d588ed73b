"""The columns and footer lines both layouts add to a table: the primary metric's 95 % CI and difference from the
reference row (:func:`significance`), and latency, parameters and MACs (:func:`costs`)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pandas as pd
from omegaconf import DictConfig

from ablate.tables.comparison import Comparison
from ablate.tables.cost import table_cost
from ablate.tables.decide import machine, undecided
from ablate.tables.frames import AP_DRAWS, FROM_DETECTIONS, verdict_metric
from ablate.tables.kept import kept
from ablate.tables.margin import kernels_margin
from ablate.tables.raceplan import RacePlan
from ablate.tables.racing import RaceState, race, race_lines, recorded_plan, seed_values
from ablate.tables.significance import (
    BOOTSTRAP_FROM,
    COLLAPSE_RATIO,
    RESAMPLES,
    Difference,
    difference,
    disagreeing_seeds,
)
from ablate.tables.spec import COSTS, LOWER_IS_BETTER
from ablate.tables.summary import best_of, fmt, per_seed, reference, signed
from ablate.tables.twolevel import FramesVariance, frames_variance
from ablate.tables.verdicts import BETTER, DIFFERENT, EQUIVALENT, UNDECIDED, WORSE, Kernels

#: The Δ column's mark of each verdict of the race (ablate.tables.verdicts).
MARKS = {BETTER: " ↑", WORSE: " ↓", EQUIVALENT: " ≈", DIFFERENT: " *", UNDECIDED: ""}
MARKS_LEGEND = (
    "the race's verdict (below): ↑ / ↓ better / worse by more than δ, ≈ equivalent within ±δ, * different but of "
    "uncertain practical size (without a δ: different beyond seed noise), no mark: undecided."
)


def tests_used(tests: set[tuple[str, bool]]) -> str:
    """The footer's name for the tests behind the Δ column, from each difference's (test, bootstrap CI or not)
    (:class:`ablate.tables.significance.Difference`): where rows of different n used a t and a bootstrap CI, once,
    with the n the bootstrap starts at."""
    kinds = sorted({kind for kind, _ in tests})
    boot = [b for _, b in tests]
    ci = (", bootstrap CI" if all(boot) else f", bootstrap CI from n = {BOOTSTRAP_FROM}") if any(boot) else ""
    return ", ".join(kinds) + ci if kinds else "no test: too few seeds"


def significance(summary: pd.DataFrame, runs: pd.DataFrame, table: DictConfig) -> tuple[dict, list[str]]:
    """The primary metric's CI column and difference-from-reference column, and the footer lines that explain
    them: the test used, whether the top row is ahead of the second beyond seed noise, and disagreeing seeds."""
    key, label = table.primary, table.metrics.get(table.primary, table.primary)
    ref = reference(summary, table)
    if ref is None:
        return {}, []
    raced = replayed_race(summary, runs, table, key)
    if raced is not None:
        ref = raced.reference or ref
    ref_name = str(summary.loc[summary["row"] == ref, "name"].iloc[0])
    cis, deltas, tests = _ci_and_delta(summary, runs, key, ref, raced, table_frames(runs, table))
    columns = {f"{label} 95% CI": cis, f"Δ {label} vs {ref_name} [95% CI]": deltas}
    lines = [
        f"95% CI: of the mean over seeds, Student's t for n < {BOOTSTRAP_FROM}, a percentile bootstrap over "
        f"seeds ({RESAMPLES} resamples) from n = {BOOTSTRAP_FROM}. Δ: difference from {ref_name} on {label} "
        f"({tests_used(tests)}; paired over the seeds two rows share); "
        + ("*: its 95% CI excludes 0." if raced is None else MARKS_LEGEND)
    ]
    if raced is not None:
        names = dict(zip(summary["row"], summary["name"]))
        lines += rope_line(table, label) + race_lines(raced, names)
        lines += [todo.words(names, machine(runs)) for todo in undecided(raced, runs).values()]
        lines.append(table_cost(raced, runs).words())
        measured = kernels(table)
        if measured.per_seed or measured.shared:
            lines.append(
                "Each seed's paired difference carries another CPU's kernels' variance too, measured by rerunning this "
                f"table's seeds on other kernels (docs/verdicts.md): an sd of {measured.per_seed:g} per seed, added to "
                + (
                    f"the seeds', and of {measured.shared:g} shared by every seed, which more seeds do not average away."
                    if measured.shared
                    else "the seeds'; none of it is shared by every seed."
                )
            )
        elif any(c.kind != UNDECIDED and c.n >= 2 for c in raced.comparisons.values()):
            rows, values = race_inputs(summary, runs, key)
            held = kernels_margin(lambda sd: replay(runs, table, rows, values, key, Kernels(shared=sd)) or raced)
            margin = f" {held.words(names, label)}" if held is not None else ""
            lines.append(KERNELS_UNMEASURED.format(cpu=machine(runs), margin=margin))
        ap = verdict_metric(table)[0] in FROM_DETECTIONS  # a conditions table's primary is <condition>/<metric>
        if any(c.frames for c in raced.comparisons.values()):
            lines.append(AP_FRAMES_LINE if ap else FRAMES_LINE)
        elif ap:
            lines.append(NO_FRAMES_LINE)
    lines += _top_against_second(summary, runs, key, label, raced, table_frames(runs, table))
    return columns, lines + _disagreeing_seed_lines(summary, runs, table)


FRAMES_LINE = (
    "The verdicts and Δ read the interval over seeds and test frames: the seeds' variance of the paired differences "
    "plus the test frames' (a delete-one jackknife over frames, the metric recomputed from each frame's counts), on "
    "Student's t with the seeds' n − 1 degrees of freedom: never narrower than the seeds' own t interval, and free "
    "of Monte Carlo error (ablate.tables.twolevel)."
)
AP_FRAMES_LINE = (
    "The verdicts and Δ read the interval over seeds and test frames: the seeds' variance of the paired differences "
    f"plus the test frames' (the variance over {AP_DRAWS} paired draws of the frames with replacement, from one fixed "
    "stream, each run's AP re-accumulated from its matched detections: AP steps with single frames, which a "
    "jackknife misjudges), on Student's t with the seeds' n − 1 degrees of freedom: never narrower than the seeds' "
    "own t interval (ablate.tables.twolevel)."
)
NO_FRAMES_LINE = (
    "The verdicts read the seeds alone: these records keep no detections per test frame (they were raced before the "
    "jobs kept them), so the test set's draw is not counted; the next race of this table adds it."
)


def rope_line(table: DictConfig, label: str) -> list[str]:
    """The footer's line on the table's region of practical equivalence: its δ and why (none without one)."""
    rope = table.get("rope") or {}
    if rope.get("delta") is None:
        return []
    reason = f": {rope['reason']}" if rope.get("reason") else ""
    delta = float(rope["delta"])
    return [f"Region of practical equivalence: ±δ = {delta:g} {label}{reason} (the rule: docs/verdicts.md)."]


def race_inputs(summary: pd.DataFrame, runs: pd.DataFrame, key: str) -> tuple[list[str], dict[str, pd.Series]]:
    """The rows a table's race replays (the summary's, in its order, that have runs) and their values of ``key`` by
    seed."""
    return [str(r) for r in summary["row"] if r in set(runs.get("row", []))], seed_values(runs, key)


def replayed_race(summary: pd.DataFrame, runs: pd.DataFrame, table: DictConfig, key: str) -> RaceState | None:
    """The race's own decisions, replayed from the runs (ablate.tables.racing); None without a race plan or rows."""
    rows, values = race_inputs(summary, runs, key)
    return replay(runs, table, rows, values, key)


def replay(
    runs: pd.DataFrame,
    table: DictConfig,
    rows: list[str],
    values: dict[str, pd.Series],
    key: str,
    measured: Kernels | None = None,
) -> RaceState | None:
    """The race of ``rows`` on their ``values`` of ``key`` as the table reports it: the plan the runs ran under,
    the table's δ (table.rope) and reference, judged on the seeds and the test frames where the runs kept counts
    per frame (:func:`ablate.tables.frames.judged`) and with the kernels' variance the table measured (``measured`` in
    its place: :mod:`ablate.tables.margin`); None without a race plan or rows."""
    plan = RacePlan.from_config(recorded_plan(runs) or table.get("seeds"))
    if plan is None or not rows:
        return None
    named = table.get("reference")
    candidates = [r for r in ([named] if isinstance(named, str) else list(named or [])) if r in rows]
    higher = key not in LOWER_IS_BETTER
    frames_var = table_frames(runs, table) if key == str(table.primary) else None
    return race(
        values,
        rows,
        candidates or rows[0],
        plan.with_rope(table),
        higher,
        frames_var=frames_var,
        kernels=kernels(table) if measured is None else measured,
    )


#: The footer's line where a raced table decided a comparison without measuring another CPU's kernels' variance.
KERNELS_UNMEASURED = (
    "Another CPU's kernels' variance is not measured for this table (bench/kernel_spread.py, docs/verdicts.md): its "
    "verdicts hold for the kernels of the CPU its records were made on, {cpu}.{margin} On other tables another CPU's "
    "kernels added about as much as the seeds' own spread."
)


def kernels(table: DictConfig) -> Kernels:
    """Another CPU's kernels' variance of each seed's paired difference, where the table measured it
    (``table.kernels_sd`` per seed, ``table.kernels_cpu`` shared by every seed: ``bench/kernel_spread.py``,
    docs/verdicts.md); 0 where it did not."""
    return Kernels(measured_sd(table, "kernels_sd"), measured_sd(table, "kernels_cpu"))


def measured_sd(table: DictConfig, key: str) -> float:
    """``table.<key>``, a measured standard deviation: a number >= 0, or 0 where it is null (not measured)."""
    value = table.get(key)
    if value is None:
        return 0.0
    if not isinstance(value, int | float) or isinstance(value, bool) or value < 0:
        raise ValueError(f"table.{key}: {value!r} must be a number >= 0 (or null: not measured)")
    return float(value)


def kernels_run(table: DictConfig) -> tuple[float, int] | None:
    """How far other numerics move one run of a seed, where the table measured it (``table.kernels_run``: ``sd``,
    the root mean square of its reruns' shifts from their records over ``seeds`` seeds, ``bench/kernel_spread.py``):
    the term a prediction interval for a run made on another CPU adds, with a degree of freedom per seed (the rows
    of a seed share its experts and move together; :func:`ablate.tables.significance.prediction_interval`); None
    where it did not."""
    value = table.get("kernels_run")
    if value is None:
        return None
    sd, seeds = value.get("sd"), value.get("seeds")
    if not isinstance(sd, int | float) or isinstance(sd, bool) or sd < 0 or not isinstance(seeds, int) or seeds < 1:
        raise ValueError(f"table.kernels_run: {value!r} must hold sd >= 0 and seeds >= 1 (or be null: not measured)")
    return float(sd), int(seeds)


def table_frames(runs: pd.DataFrame, table: DictConfig) -> FramesVariance | None:
    """The test frames' variance of a table's primary metric, from the counts per frame its runs kept
    (``runs.attrs["frames"]``, put there by the table's writer: :mod:`ablate.tables.kept`;
    :mod:`ablate.tables.twolevel`); None without."""
    frames, detections = kept(runs, "frames"), kept(runs, "detections")
    frames = frames if isinstance(frames, pd.DataFrame) else None
    detections = detections if isinstance(detections, pd.DataFrame) else None
    primary, condition = verdict_metric(table)
    terms = kept(runs, "frames_terms")  # one term per table rendering: an AP term's draws are its cost
    if not isinstance(terms, dict):
        return frames_variance(frames, primary, condition, detections)
    if (primary, condition) not in terms:
        terms[(primary, condition)] = frames_variance(frames, primary, condition, detections)
    return terms[(primary, condition)]


def pair_frames(frames_var: FramesVariance | None, a: str, b: str) -> Callable[[list[int]], float] | None:
    """``frames_var`` for the pair ``a - b`` as a function of the seeds (:func:`ablate.tables.significance.difference`)."""
    return None if frames_var is None else (lambda seeds: frames_var(a, b, seeds))


def at_look(values: pd.Series, raced: RaceState | None, c: Comparison | None) -> pd.Series:
    """``values`` (by seed) cut to the seeds of the look where the race left comparison ``c``: a figure shown beside a
    verdict is the one the verdict was reached on."""
    if raced is None or c is None:
        return values
    n = raced.plan.looks[c.look - 1]
    seeds = pd.to_numeric(pd.Series(values.index, dtype=str), errors="coerce").to_numpy()
    return values[(seeds >= 0) & (seeds < n)]


def _ci_and_delta(
    summary: pd.DataFrame,
    runs: pd.DataFrame,
    key: str,
    ref: str,
    raced: RaceState | None,
    frames_var: FramesVariance | None = None,
) -> tuple[list[str], list[str], set[tuple[str, bool]]]:
    """Each row's 95 % CI and difference from ``ref`` (starred when significant, or decided by the race), and the
    (test, bootstrap CI or not) of the differences for :func:`tests_used`."""
    cis: list[str] = []
    deltas: list[str] = []
    tests: set[tuple[str, bool]] = set()
    for row, lo, hi in zip(summary["row"], summary[f"{key}_lo"], summary[f"{key}_hi"]):
        cis.append("—" if np.isnan(lo) else f"[{lo:.2f}, {hi:.2f}]")
        if row == ref:
            deltas.append("reference")
            continue
        d = row_difference(runs, key, row, ref, raced, frames_var)
        if np.isnan(d.ci.lo):
            deltas.append("—" if np.isnan(d.delta) else signed(d.delta))
            continue
        tests.add((d.test.removesuffix(", bootstrap CI"), d.ci.method == "bootstrap"))
        mark = (" *" if d.significant else "") if raced is None else MARKS[kind_of(raced, row, ref)]
        deltas.append(f"{signed(d.delta)} [{signed(d.ci.lo)}, {signed(d.ci.hi)}]" + mark)
    return cis, deltas, tests


def row_difference(
    runs: pd.DataFrame, key: str, row: str, ref: str, raced: RaceState | None, frames_var: FramesVariance | None
) -> Difference:
    """``row`` minus ``ref`` on ``key`` (:func:`ablate.tables.significance.difference`), over the seeds of the look
    where the race left their comparison, with the test frames' variance where the runs kept counts and the kernels'
    where the table measured it (as the race reads them)."""
    c = raced.comparisons.get(frozenset((row, ref))) if raced is not None else None
    a, b = (at_look(per_seed(runs, r, key), raced, c) for r in (row, ref))
    return difference(a, b, pair_frames(frames_var, row, ref), c.kernels if c is not None else Kernels())


def top_and_second(
    summary: pd.DataFrame,
    runs: pd.DataFrame,
    key: str,
    raced: RaceState | None,
    frames_var: FramesVariance | None = None,
) -> tuple[str, str, Difference, str] | None:
    """The top row's and the second's names (the race's where it ranked them, else by mean), their difference on
    ``key``, and the verdict on the top row against the second (:mod:`ablate.tables.verdicts`: the race's where
    there is one, else ``different`` where the 95 % CI of the difference excludes 0); None under two rows."""
    ranked = summary.dropna(subset=[f"{key}_mean"]).sort_values(
        f"{key}_mean", ascending=key in LOWER_IS_BETTER, kind="stable"
    )
    if len(ranked) < 2:
        return None
    (top, top_name), (second, second_name) = [tuple(r) for r in ranked[["row", "name"]].iloc[:2].to_numpy()]
    if raced is not None and raced.top:
        names = dict(zip(summary["row"], summary["name"]))
        (top, second), (top_name, second_name) = raced.top, (names[raced.top[0]], names[raced.top[1]])
    d = row_difference(runs, key, top, second, raced, frames_var)
    kind = (DIFFERENT if d.significant else UNDECIDED) if raced is None else kind_of(raced, top, second)
    return str(top_name), str(second_name), d, kind


def kind_of(raced: RaceState, a: str, b: str) -> str:
    """The race's verdict on ``a`` against ``b``, as ``a``'s (better where ``a`` is ahead by more than δ)."""
    c = raced.comparisons.get(frozenset((a, b)))
    if c is None:
        return UNDECIDED
    flip = {BETTER: WORSE, WORSE: BETTER}
    return c.kind if c.a == a else flip.get(c.kind, c.kind)


def ahead_words(d: Difference, kind: str, rope: float | None = None) -> str:
    """The top row against the second, in the words of the footer and the results summary."""
    if np.isnan(d.ci.lo):
        return "n/a (too few seeds)"
    if kind == BETTER:
        return f"ahead by more than δ = {rope:g}"
    if kind == EQUIVALENT:
        return f"equivalent to it within ±{rope:g}"
    if kind == DIFFERENT:
        return "ahead beyond seed noise" + (", of uncertain practical size" if rope is not None else "")
    return "not separable from seed noise"


def _top_against_second(
    summary: pd.DataFrame,
    runs: pd.DataFrame,
    key: str,
    label: str,
    raced: RaceState | None,
    frames_var: FramesVariance | None = None,
) -> list[str]:
    """The footer line on the top row against the second (none under two rows): the figures the verdict was reached
    on (the race's comparison, at its look and level), so its words never claim more than its interval and p."""
    found = top_and_second(summary, runs, key, raced, frames_var)
    if found is None:
        return []
    top_name, second_name, d, kind = found
    said = ahead_words(d, kind, raced.plan.rope if raced is not None else None)
    top = raced.top if raced is not None else None
    c = raced.comparisons.get(frozenset(top)) if raced is not None and top else None
    if np.isnan(d.ci.lo):
        verdict = said
    elif c is not None and top is not None and c.n >= 2:
        sign = 1 if c.a == top[0] else -1
        lo, hi = sorted((sign * c.lo, sign * c.hi))
        share = f"{100 * (1 - 2 * c.level):.1f}%"
        verdict = (
            f"{signed(sign * c.delta)} [{signed(lo)}, {signed(hi)}], the unadjusted {share} interval ({d.test}, n = {c.n}), "
            f"p = {c.p:.3g} {c.p_words()} against {c.level:.4f} at look {c.look}: {said} (the race's verdict)"
        )
    else:
        verdict = f"{signed(d.delta)} [{signed(d.ci.lo)}, {signed(d.ci.hi)}], {d.test}, p = {d.p:.3f}: " + said
    return [f"Top row {top_name} against the second, {second_name}, on {label}: {verdict}."]


def _disagreeing_seed_lines(summary: pd.DataFrame, runs: pd.DataFrame, table: DictConfig) -> list[str]:
    """A warning per seed whose metric collapsed against the median of its row's other seeds (a failed seed)."""
    lines: list[str] = []
    for row, name in zip(summary["row"], summary["name"]):
        for k, lab in table.metrics.items():
            if k in LOWER_IS_BETTER:
                continue
            for seed, v, med in disagreeing_seeds(per_seed(runs, row, k)):
                lines.append(
                    f"**Seeds disagree**: {name}, {lab}, seed {seed} gives {v:.2f} against a median of "
                    f"{med:.2f} over its other seeds (below {COLLAPSE_RATIO:.0%} of it); the row's mean "
                    "hides a failed seed."
                )
    return lines


def costs(summary: pd.DataFrame, runs: pd.DataFrame, table: DictConfig) -> tuple[dict, list[str]]:
    """Latency (median [interquartile range] over the interleaved rounds, and its ratio to the reference row),
    parameters and MACs per row, with a footer saying how latency was measured and warning of a loaded machine."""
    if not len(summary):
        return {}, []
    columns: dict[str, list[str]] = {}

    def per_row(key: str) -> list[float]:
        return [per_seed(runs, row, key).mean() if key in runs else np.nan for row in summary["row"]]

    med, q1, q3 = per_row("latency_ms"), per_row("latency_q1_ms"), per_row("latency_q3_ms")
    label = table.metrics.get("latency_ms", COSTS["latency_ms"])
    best = np.nanmin(med) if not np.all(np.isnan(med)) else np.nan
    columns[f"{label} (ours)"] = [
        "—" if np.isnan(m) else (f"**{m:.2f}**" if m == best else f"{m:.2f}") + f" [{a:.2f}, {b:.2f}]"
        for m, a, b in zip(med, q1, q3)
    ]
    paper = summary["latency_ms_paper"] if "latency_ms_paper" in summary else pd.Series(dtype=float)
    if paper.notna().any():
        columns[f"{label} (paper)"] = [fmt(v, np.nan, v == best_of(paper, "latency_ms")) for v in paper]
    ref = reference(summary, table)
    ref_med = med[list(summary["row"]).index(ref)] if ref is not None else np.nan
    if not np.isnan(ref_med):
        columns[f"{label} ratio"] = ["—" if np.isnan(m) else f"{m / ref_med:.2f}×" for m in med]
    for key in ("params_m", "macs_g"):
        values = per_row(key)
        if not np.all(np.isnan(values)):
            columns[table.metrics.get(key, COSTS[key])] = ["—" if np.isnan(v) else f"{v:.2f}" for v in values]
    lines = []
    if np.all(np.isnan(med)):
        if not table.rows:  # an ad-hoc sweep: no experiment to name, no rows to load side by side
            lines.append(
                f"{label}: not measured (an ad-hoc sweep; `python -m ablate.latency` times an experiment's rows)."
            )
        else:
            lines.append(
                f"{label}: not measured yet (`python -m ablate.latency experiment={table.name}`, with the sweep's "
                "`hydra.searchpath=[file://...]` where its experiment lives in a folder of your own)."
            )
        return columns, lines
    load, cores = runs.get("latency_load", pd.Series(dtype=float)).max(), runs["latency_cores"].max()
    rounds = (
        f"{label}: median [interquartile range] of one forward pass at batch 1, every row timed side by side "
        "in one process, interleaved (`python -m ablate.latency`); ratio to the reference row. "
        f"Load average up to {load:.1f} on {cores:.0f} cores."
    )
    lines.append(
        rounds
        + (
            f" **Loaded machine**: the load exceeded the {cores:.0f} available cores while timing; "
            "rerun `python -m ablate.latency` on a quiet machine."
            if load > cores
            else ""
        )
    )
    return columns, lines
