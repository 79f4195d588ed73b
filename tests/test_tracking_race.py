"""A fresh SQLite store survives parallel first use: MLflow creates its schema on first use, which two processes
cannot do at once, so Tracker serialises it with a file lock beside the database."""

import multiprocessing as mp


def _job(args):
    uri, k = args
    from ablate.store.tracker import Tracker

    tracker = Tracker(uri)
    run_id = tracker.start(tracker.experiment_id("race"), f"job {k}", {"k": str(k)})
    tracker.end(run_id, "FINISHED")
    return run_id


def test_four_processes_on_a_fresh_sqlite_store_lose_no_run(tmp_path):
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    with mp.get_context("spawn").Pool(4) as pool:  # without the lock: "duplicate column name: step" and kin
        ids = pool.map(_job, [(uri, k) for k in range(4)], chunksize=1)
    from ablate.store.tracker import Tracker

    tracker = Tracker(uri)
    runs = tracker.runs(tracker.experiment_id("race"))
    assert sorted(r.info.run_id for r in runs) == sorted(ids)
    assert {r.info.status for r in runs} == {"FINISHED"} and {r.data.tags["k"] for r in runs} == {"0", "1", "2", "3"}
    assert (tmp_path / "mlflow.db-lock").exists()
