"""Your runs of a paper table beside the published ones: does your machine give the published numbers?

``make run`` races BiFNet Table IV on the user's machine and ends here instead of overwriting the published table:
for each row, the user's mean of the table's primary metric beside the published mean (from the committed records,
:mod:`ablate.tables.records`), how many of the user's seeds lie inside the published row's 95 % prediction interval
for a new seed (:func:`ablate.tables.significance.prediction_interval`: the range one new run should fall in), and
which of CPU, ISA, precision and threads differ from the published runs', and whether each row ran the published
config: compared by its hash (the same config whatever route set its values: ``make run`` races each row on its
published config, ``table.tuned_from=published``), else by the tuned config (a published row raced on the config a
tuning phase chose for it, :mod:`ablate.sweep.tuning`, beside a row raced on the recipe). Results follow the
instruction set's kernels and the thread count (a reduction adds in another order), so a machine of another ISA is
expected to give other numbers for the same seed, inside the interval rather than equal to it. Training amplifies
that rounding until a seed moves as far as another seed does, or further (docs/verdicts.md): where your runs'
numerics differ from the published ones' and the table measured how far that moves a run (``table.kernels_run``),
the interval adds it (:func:`ablate.tables.columns.kernels_run`), and its column says so.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
from omegaconf import DictConfig

from ablate.tables.collect import under_condition
from ablate.tables.columns import kernels_run
from ablate.tables.records import numerics_differ, read_records, records_path
from ablate.tables.significance import prediction_interval
from ablate.tables.tuning import config_text


def compare(mine: pd.DataFrame, published: pd.DataFrame, table: DictConfig) -> str:
    """Markdown: per row of ``table`` that both have, the means of the primary metric, the user's seeds inside the
    published prediction interval, and the numerics or tuned config that differ."""
    key = str(table.primary)
    mine, published = under_condition(mine, table), under_condition(published, table)
    differ = bool(numerics_differ(published, mine))
    rounding = kernels_run(table) if differ else None
    widened = f", with other numerics' sd {rounding[0]:g} ({rounding[1]} seeds)" if rounding else ""
    lines = [
        f"| Row | Yours (mean, n) | Published (mean, n) | Published 95 % PI for a new seed{widened} | "
        "Your seeds inside | Numerics that differ; config |",
        "|:--|--:|--:|:--|--:|:--|",
    ]
    for spec in table.rows:
        row = str(spec["row"])
        a, b = mine[mine["row"] == row], published[published["row"] == row]
        if not len(a) or not len(b) or key not in a or key not in b:
            continue
        lo, hi = prediction_interval(b[key], rounding)
        if np.isnan(lo):  # one published seed: no interval
            interval, inside = "— (needs 2 published seeds)", "—"
        else:
            interval, inside = f"[{lo:.2f}, {hi:.2f}]", f"{int(((a[key] >= lo) & (a[key] <= hi)).sum())} of {len(a)}"
        lines.append(
            f"| {spec.get('name', row)} | {a[key].mean():.2f} ({len(a)}) | {b[key].mean():.2f} ({len(b)}) | "
            f"{interval} | {inside} | {differing(a, b) or 'none'} |"
        )
    if differ and rounding is None:
        lines += ["", UNMEASURED]
    return "\n".join(lines) + "\n"


#: Under a comparison whose numerics differ where the table did not measure what that does to a run.
UNMEASURED = (
    "Your numerics differ from the published runs' (last column), and this table has not measured how far that "
    "moves a run (`table.kernels_run`, `bench/kernel_spread.py`): the interval is another seed's on the published "
    "numerics, and a seed of yours outside it may be the numerics' doing."
)


def differing(mine: pd.DataFrame, published: pd.DataFrame) -> str:
    """``name: published -> yours`` for each of :data:`ablate.tables.records.NUMERICS` whose values differ, then the
    config: ``same config`` where every seed both have ran the published config hash (however its values were
    set: a tuning phase, or its draws given on the command line), else the scale where it differs (its config then
    differs whatever the tuned values: a run raced on the published config at ``scale=smoke`` records only what it
    set beyond the recipe), else the tuned configs where they differ (``the recipe`` for an untuned row,
    :func:`ablate.tables.tuning.config_text`), else that the hashes differ."""
    out = numerics_differ(published, mine)
    same = same_config(mine, published)
    if same:
        return "; ".join([*out, "same config"])
    scales = [sorted({str(s) for s in runs.get("scale", pd.Series(dtype=str)).dropna()}) for runs in (published, mine)]
    if all(scales) and scales[0] != scales[1]:
        return "; ".join([*out, f"another scale: {' / '.join(scales[0])} -> {' / '.join(scales[1])}"])
    before, now = (
        sorted({config_text(str(c)) for c in runs.get("tuned_config", pd.Series([""])).fillna("")})
        for runs in (published, mine)
    )
    if before != now:
        out.append(f"tuned config: {' / '.join(before)} -> {' / '.join(now)}")
    elif same is False:
        out.append("another config (its hash differs from the published one's at the same seed)")
    return "; ".join(out)


def same_config(mine: pd.DataFrame, published: pd.DataFrame) -> bool | None:
    """Whether each seed both have ran the same config (hash, :func:`ablate.store.config_hash`: the seed is part of
    it); None where they share no seed or the records carry no hash."""
    if "config_hash" not in mine or "config_hash" not in published:
        return None
    a, b = (runs.dropna(subset=["config_hash"]).groupby("seed")["config_hash"].agg(set) for runs in (mine, published))
    shared = sorted(set(a.index) & set(b.index))
    if not shared:
        return None
    return all(a[seed] == b[seed] for seed in shared)


def against_published(mine: pd.DataFrame, table: DictConfig, results: Path) -> str | None:
    """The comparison of ``mine`` with the published records of ``table`` under ``results``; None where it has
    none."""
    path = records_path(results, str(table.name))
    if not path.exists() or not len(mine):
        return None
    title = f"# Your {table.name} beside the published one ({path})\n\n"
    return title + compare(mine, read_records(path), table)
