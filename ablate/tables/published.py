"""What is published, and the one route that writes it: the results folder (:data:`ablate.config.RESULTS`),
the list of experiments (:func:`experiments`, the tables of ``conf/experiment/``), and every file written under the
folder: a table and its records from the store (:func:`publish`), a table from its committed records
(:func:`render`), the results summary (:func:`summary`), the records' seal (:func:`seal`), a parity section
(:func:`parity`), and the other commands' text and figures (:func:`write_text`, :func:`write_figure`: the paper
check's ``paper_scale.md``, a table's diagnosis).

The tables room renders into any folder it is given (a sweep's own folder, a test's); what lands under
``results/`` goes through here.
"""

from __future__ import annotations

import shutil
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from ablate.config import CONF, RESULTS  # noqa: E402  (RESULTS: the results folder, named there alone)
from ablate.tables import render_records, write_table  # noqa: E402
from ablate.tables.index import write_index  # noqa: E402
from ablate.tables.parity import Parity, write_parity  # noqa: E402
from ablate.tables.records import check_records, records_path, reseal_records  # noqa: E402

if TYPE_CHECKING:
    import pandas as pd
    from matplotlib.figure import Figure
    from omegaconf import DictConfig

    from ablate.store import Tracker
    from ablate.tables.provenance import Recompute

#: The project's README beside the folder, whose results summary is rewritten with the folder's.
README = Path("README.md")


def experiments() -> list[str]:
    """The tables, by name: ``conf/experiment/*.yaml``, sorted."""
    return sorted(p.stem for p in (CONF / "experiment").glob("*.yaml"))


def with_tables(results: Path = RESULTS) -> list[str]:
    """The tables of :func:`experiments` with a markdown file under ``results``: the ones its summary lists
    (:func:`ablate.tables.index.write_index`). A paper table's name is its experiment's file name
    (tests/test_records.py), so the others need not be composed."""
    return [name for name in experiments() if (results / f"{name}.md").is_file()]


def path(name: str) -> Path:
    """``name`` under the results folder (read from where a command reads what was published)."""
    return RESULTS / name


def records(table: str) -> Path:
    """The published records of ``table`` (:func:`ablate.tables.records.records_path`)."""
    return records_path(RESULTS, table)


def check(table: str) -> None:
    """Raise :class:`~ablate.tables.seal.BrokenRecords` where ``table``'s published records are not what was
    written (:func:`ablate.tables.records.check_records`)."""
    check_records(RESULTS, table)


def seal(table: str) -> Path | None:
    """Seal ``table``'s published records again after an intended edit, once each file parses
    (:func:`ablate.tables.records.reseal_records`); the seal, None where the table has no records."""
    return reseal_records(RESULTS, table)


def render(
    cfg: DictConfig,
    fingerprint: Recompute | None,
    config: Callable[[pd.DataFrame], Callable[[str], DictConfig]] | None,
) -> list[Path] | None:
    """``cfg``'s table from its published records alone (:func:`ablate.tables.render_records`); None where it has
    none."""
    return render_records(cfg, RESULTS, fingerprint, config)


def publish(
    cfg: DictConfig, tracker: Tracker, parent_run: str | None, fingerprint: Recompute | None, records: bool = True
) -> list[Path]:
    """``cfg``'s table from the store's runs, its records (``records``) written and sealed first
    (:func:`ablate.tables.write_table`); the paths written."""
    return write_table(cfg, tracker, parent_run, RESULTS, fingerprint, publish=records)


def copy_in(paths: list[Path], source: Path, results: Path = RESULTS) -> list[Path]:
    """Copy a sweep's table, its records and figures (``paths``, under its folder ``source``) into ``results`` (the
    launch directory's results folder), each at its path under ``source``; the copies."""
    copies = []
    for found in paths:
        target = results / found.relative_to(source)
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(found, target)
        copies.append(target)
    return copies


def summary(tables: list[DictConfig]) -> list[Path]:
    """The results summary of ``tables`` (their specs) in the folder's README and in :data:`README`
    (:func:`ablate.tables.index.write_index`); the files written."""
    return write_index(tables, RESULTS, README)


def parity(found: Parity) -> Path:
    """A row's bf16-against-fp32 section of ``precision_parity.md`` (:func:`ablate.tables.parity.write_parity`)."""
    return write_parity(found, path("precision_parity.md"))


def write_text(name: str, text: str) -> Path:
    """Write ``text`` to ``name`` under the results folder; the path."""
    target = path(name)
    target.parent.mkdir(parents=True, exist_ok=True)
    target.write_text(text)
    return target


def write_figure(name: str, fig: Figure) -> Path:
    """Save ``fig`` as ``name`` under the results folder, with no metadata (the same figure, the same bytes), and
    close it; the path."""
    target = path(name)
    target.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(target, dpi=100, metadata={"Software": None})
    plt.close(fig)
    return target
