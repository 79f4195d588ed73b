"""Learning curves per table: each row's primary validation metric and training loss per epoch, mean over its seeds
with a band from the lowest to the highest seed, one line per row (``<table>_curves.png``).

The curves are read from the runs' metric histories when a table is published from the store (:func:`from_store`:
``val/<primary>`` per epoch, and ``train/loss`` per step averaged over each epoch, an epoch's steps being those up to
its validation's step) and kept beside the table's records (``runs/<table>.curves.csv``: run, row, seed, metric,
epoch, value; per epoch, never per step), so that the figure renders again from the records alone.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402
from matplotlib.ticker import MaxNLocator  # noqa: E402
from omegaconf import DictConfig  # noqa: E402

from ablate.store import Tracker  # noqa: E402
from ablate.tables.records import RUNS_DIR  # noqa: E402
from ablate.tables.seal import write_csv  # noqa: E402
from ablate.tables.spec import row_names  # noqa: E402

COLUMNS = ["run_id", "row", "seed", "metric", "epoch", "value"]
#: The training loss's name in a run's history.
TRAIN_LOSS = "train/loss"


def curves_path(results_dir: str | Path, table: str) -> Path:
    """The curves kept beside a table's records."""
    return Path(results_dir) / RUNS_DIR / f"{table}.curves.csv"


def from_store(tracker: Tracker, runs: pd.DataFrame, table: DictConfig) -> pd.DataFrame:
    """Per run of ``runs`` (a table's records), its validation metric and training loss per epoch
    (:data:`COLUMNS`); runs without history (copied from another table: their source's) give none of their own."""
    monitor = f"val/{table.primary}"
    out = []
    for _, run in runs.iterrows():
        source = str(run.get("reused_from") or "") or str(run["run_id"])
        val = sorted((m.step, m.value) for m in tracker.metric_history(source, monitor))
        ends = [step for step, _ in val]
        out += [(run["run_id"], run["row"], run["seed"], monitor, epoch, v) for epoch, (_, v) in enumerate(val)]
        loss = pd.DataFrame([(m.step, m.value) for m in tracker.metric_history(source, TRAIN_LOSS)], columns=["s", "v"])
        if len(loss) and ends:
            epoch = np.searchsorted(np.asarray(ends), loss["s"].to_numpy(), side="left")
            for e, v in loss.groupby(epoch)["v"].mean().items():
                if e < len(ends):
                    out.append((run["run_id"], run["row"], run["seed"], TRAIN_LOSS, int(e), float(v)))
    return pd.DataFrame(out, columns=COLUMNS)


def write_curves(curves: pd.DataFrame, results_dir: str | Path, table: str) -> Path:
    """``runs/<table>.curves.csv``, sealed (:func:`ablate.tables.seal.write_csv`)."""
    return write_csv(curves, curves_path(results_dir, table))


def read_curves(path: Path) -> pd.DataFrame:
    return pd.read_csv(path, dtype={"run_id": str, "row": str, "seed": str, "metric": str})


def plot(curves: pd.DataFrame, table: DictConfig) -> Figure:
    """Two panels, the validation metric and the training loss per epoch: per row its mean over seeds, and a band
    from its lowest to its highest seed."""
    monitor = f"val/{table.primary}"
    names = row_names(table)
    order = [r for r in names if r in set(curves["row"])] or sorted(set(curves["row"]))
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.4))
    for ax, metric, label in (
        (axes[0], monitor, f"validation {table.metrics.get(table.primary, table.primary)}"),
        (axes[1], TRAIN_LOSS, "training loss (mean over each epoch's steps)"),
    ):
        sel = curves[curves["metric"] == metric]
        for k, row in enumerate(order):
            per = sel[sel["row"] == row].groupby("epoch")["value"].agg(["mean", "min", "max"])
            if per.empty:
                continue
            x = per.index.to_numpy() + 1
            ax.plot(x, per["mean"], marker=".", color=f"C{k % 10}", label=names.get(row, row))
            ax.fill_between(x, per["min"], per["max"], color=f"C{k % 10}", alpha=0.2, linewidth=0)
        ax.set_xlabel("epoch")
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))
        ax.set_ylabel(label, fontsize=8)
    axes[0].legend(fontsize=7)
    fig.suptitle(f"{table.title}: learning curves (mean over seeds, band: lowest to highest seed)", fontsize=9)
    fig.tight_layout()
    return fig


def write_figure(curves: pd.DataFrame, table: DictConfig, out: Path) -> Path | None:
    """``<table>_curves.png`` under ``out``; None without curves."""
    if not len(curves):
        return None
    path = out / f"{table.name}_curves.png"
    fig = plot(curves, table)
    fig.savefig(path, dpi=100, metadata={"Software": None})
    plt.close(fig)
    return path
