"""A sweep whose rows come from the sweeper's ``params`` (a user's experiment, no ``row`` key): the jobs tag their runs
with the rows the race looks up (:func:`ablate.store.row_name`, shared by the job and the racing sweeper), so the
race reads every row's values and the table lists the rows the user swept."""

from __future__ import annotations

from pathlib import Path

from tests.scaleout import SERIAL, TINY, ablate, output, runs

EXPERIMENT = """\
# @package _global_
defaults:
  - override /task: semantic
table:
  name: mine
  title: Two models swept through the sweeper's params
  seeds: {looks: [1], alpha: 0.05, correction: bonferroni, budget_min: null}
hydra:
  sweeper:
    params:
      model: unet,fusenet
"""


def test_a_sweep_through_the_sweepers_params_races_and_tabulates_the_rows_swept(tmp_path: Path) -> None:
    (tmp_path / "myconf" / "experiment").mkdir(parents=True)
    (tmp_path / "myconf" / "experiment" / "mine.yaml").write_text(EXPERIMENT)
    out = ablate(tmp_path, "-m", "experiment=mine", *TINY, SERIAL, "hydra.searchpath=[file://myconf]")
    assert out.returncode == 0, output(out)
    _, found = runs(f"sqlite:///{tmp_path / 'mlflow.db'}", "mine")
    assert sorted(r.data.tags["row"] for r in found) == ["model=fusenet", "model=unet"]
    assert "gave no values" not in out.stderr + out.stdout  # the race found both rows' values after its look
    table = (tmp_path / "results" / "mine.md").read_text()
    assert "model=unet" in table and "model=fusenet" in table
