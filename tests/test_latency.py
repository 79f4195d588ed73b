"""Side-by-side latency: interleaved rounds with a fake clock, quartiles, MACs, and the loaded-machine warning."""

import pandas as pd
import pytest
import torch
from omegaconf import OmegaConf

from ablate.analysis.latency import interleaved, machine_load, macs, quartiles
from ablate.tables.rows import to_markdown
from ablate.tables.summary import summarise
from tests.stores import sqlite_uri


class FakeClock:
    """Time advances only when a forward pass runs: by the row's cost, plus a load burst in some rounds."""

    def __init__(self):
        self.now, self.calls = 0.0, []

    def __call__(self):
        return self.now

    def forward(self, name, cost, burst=lambda: 0.0):
        def run():
            self.calls.append(name)
            self.now += cost + burst()

        return run


def test_rounds_interleave_rows_in_rotated_order_after_warmup():
    clock = FakeClock()
    forwards = {n: clock.forward(n, c) for n, c in [("a", 0.010), ("b", 0.020), ("c", 0.005)]}
    times = interleaved(forwards, rounds=4, warmup=2, clock=clock)
    assert clock.calls[:9] == ["a", "b", "c", "b", "c", "a", "c", "a", "b"]  # each round starts one row later
    assert len(clock.calls) == 3 * 6
    assert {n: len(t) for n, t in times.items()} == {"a": 4, "b": 4, "c": 4}
    assert times["a"] == pytest.approx([10.0] * 4) and times["b"] == pytest.approx([20.0] * 4)


def test_a_load_burst_hits_every_row_alike_and_the_median_ignores_it():
    clock = FakeClock()
    calls = {"n": 0}

    def burst():  # the 4th and 5th round (3 rows each, after 1 warm-up round) run on a loaded machine
        calls["n"] += 1
        return 0.5 if 10 <= calls["n"] <= 15 else 0.0

    forwards = {n: clock.forward(n, c, burst) for n, c in [("a", 0.010), ("b", 0.020), ("c", 0.030)]}
    times = interleaved(forwards, rounds=9, warmup=1, clock=clock)
    for name, cost in [("a", 10.0), ("b", 20.0), ("c", 30.0)]:
        assert sum(t > 100 for t in times[name]) == 2  # the burst lands on two rounds of every row
        assert quartiles(times[name])[1] == pytest.approx(cost)


def test_quartiles():
    assert quartiles([1.0, 2.0, 3.0, 4.0, 5.0]) == pytest.approx((2.0, 3.0, 4.0))
    assert quartiles([7.0]) == (7.0, 7.0, 7.0)


def test_macs_of_a_convolution():
    conv = torch.nn.Conv2d(3, 8, 3, padding=1, bias=False)

    class Model(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.conv = conv

        def forward(self, batch):
            return self.conv(batch["rgb"])

    assert macs(Model(), {"rgb": torch.zeros(1, 3, 10, 10)}) == 8 * 3 * 9 * 10 * 10


def test_machine_load():
    load, cores = machine_load()
    assert load >= 0 and cores >= 1


def _table_with_latency(load):
    table = OmegaConf.create(
        {
            "name": "t",
            "title": "T",
            "primary": "ap",
            "reference": "a",
            "metrics": {"ap": "AP", "latency_ms": "Comp Time (ms)", "params_m": "Params (M)", "macs_g": "MACs (G)"},
            "rows": [
                {"row": "a", "name": "A", "paper": {"latency_ms": 82}},
                {"row": "b", "name": "B", "paper": {"latency_ms": 192}},
            ],
        }
    )
    runs = pd.DataFrame.from_records(
        [
            {
                "row": r,
                "seed": str(s),
                "scale": "cpu",
                "git_commit": "c" * 40,
                "ap": 50.0 + s,
                "latency_ms": ms,
                "latency_q1_ms": ms - 1,
                "latency_q3_ms": ms + 2,
                "latency_load": load,
                "latency_cores": 2.0,
                "params_m": 1.5,
                "macs_g": 0.25,
            }
            for r, ms in [("a", 10.0), ("b", 25.0)]
            for s in range(2)
        ]
    )
    return to_markdown(summarise(runs, table), runs, table)


def test_latency_column_has_median_iqr_ratio_and_paper():
    text = _table_with_latency(load=0.5)
    rows: dict[str, str] = {}  # a row's line in the main table and in "All metrics", together
    for line in text.splitlines():
        if line.startswith("| "):
            rows[line.split("|")[1].strip()] = rows.get(line.split("|")[1].strip(), "") + line
    assert "**10.00** [9.00, 12.00]" in rows["A"] and "25.00 [24.00, 27.00]" in rows["B"]
    assert "2.50×" in rows["B"] and "1.00×" in rows["A"]
    assert "192.00" in rows["B"] and "0.25" in rows["B"]
    assert "Load average up to 0.5 on 2 cores." in text and "Loaded machine" not in text


def test_a_loaded_machine_is_flagged_under_the_table():
    assert "**Loaded machine**" in _table_with_latency(load=6.3)


def test_a_reused_run_is_timed_from_its_source_runs_checkpoint(tmp_path, monkeypatch):
    from ablate.analysis.latency import row_checkpoint
    from ablate.store.tracker import Tracker

    monkeypatch.chdir(tmp_path)
    tracker = Tracker(sqlite_uri(tmp_path), str(tmp_path / "artifacts"))
    source_id = tracker.start(
        tracker.experiment_id("table_a"), "dgfn seed=0", {"table": "table_a", "config_hash": "abc", "kind": "job"}
    )
    tracker.end(source_id, "FINISHED")
    copy_id = tracker.copy_run(tracker.get_run(source_id), tracker.experiment_id("table_b"), {"table": "table_b"})
    copy = tracker.get_run(copy_id)
    assert row_checkpoint(tracker, copy) is None  # neither checkpoint on this machine
    ckpt = tmp_path / "checkpoints" / "table_a" / "abc" / "best.ckpt"
    ckpt.parent.mkdir(parents=True)
    ckpt.write_bytes(b"")
    assert row_checkpoint(tracker, copy) == ckpt.relative_to(tmp_path)
