"""A tracking server that does not answer, without a server: the outbox delivers each batch once and in order, a
crash between delivering and marking sends nothing twice, the training-time logger never waits, the waiting of
:func:`retry` is bounded and named, and a job's end waits in the outbox for the next job to deliver."""

import json
import socket
import time

import pytest
import requests
from mlflow.exceptions import MlflowException

from ablate.jobs.record import deliver_earlier, kept_for_later, record_end, unreachable
from ablate.store import Outbox, RunLogger, ServerUnreachable, Tracker
from ablate.store import retry as retry_module
from ablate.store import run_logger as logger_module
from ablate.store.outage import shown, symptom
from ablate.store.retry import retry
from tests.stores import sqlite_uri

REFUSED = (
    "API request to http://127.0.0.1:5999/api/2.0/mlflow/runs/log-batch failed with exception "
    "HTTPConnectionPool(host='127.0.0.1', port=5999): Max retries exceeded with url: /api/2.0/mlflow/runs/log-batch "
    "(Caused by NewConnectionError('Failed to establish a new connection: [Errno 111] Connection refused'))"
)


@pytest.fixture(scope="module")
def tracker(tmp_path_factory):
    """One SQLite store for the module (creating one takes seconds); each test makes runs of its own."""
    folder = tmp_path_factory.mktemp("store")
    return Tracker(sqlite_uri(folder), str(folder / "artifacts"), outage_s=2)


def new_run(tracker):
    return tracker.start(tracker.experiment_id("outage"), "r", {"kind": "job"})


class Down:
    """Make ``tracker``'s client refuse every call while ``down`` is true, as a stopped server does."""

    def __init__(self, tracker, monkeypatch):
        self.down, self.calls = False, 0
        for name in ("log_batch", "set_terminated"):
            real = getattr(tracker._client, name)  # the store's own client: the faults are injected under it
            monkeypatch.setattr(tracker._client, name, self.wrap(real))

    def wrap(self, real):
        def call(*args, **kwargs):
            self.calls += 1
            if self.down:
                raise MlflowException(REFUSED)
            return real(*args, **kwargs)

        return call


def history(tracker, run_id, key):
    return [(m.step, m.value, m.timestamp) for m in tracker.metric_history(run_id, key)]


def test_batches_are_delivered_in_order_and_the_outbox_is_removed_after(tmp_path):
    box = Outbox(tmp_path / "outbox.jsonl")
    for i in range(3):
        box.add("run", [("m", float(i), 1000 + i, i)])
    box.add("run", tags={"error": "x"}, status="FAILED")
    assert box.pending == 4 and box.values() == 3
    seen = []
    done = box.deliver(seen.append)
    assert [b.seq for b in seen] == [1, 2, 3, 4] == [b.seq for b in done]
    assert [b.metrics[0][1] for b in seen[:3]] == [0.0, 1.0, 2.0] and seen[3].status == "FAILED"
    assert not box.path.exists() and box.pending == 0 and box.deliver(seen.append) == []


def test_a_failed_send_stops_the_delivery_and_the_rest_waits_in_order(tmp_path):
    box = Outbox(tmp_path / "outbox.jsonl")
    for i in range(4):
        box.add("run", [("m", float(i), 1000 + i, i)])
    sent = []

    def send(batch):
        if batch.seq == 3:
            raise ServerUnreachable("http://h:1", 0, 0, "connection refused")
        sent.append(batch.seq)

    with pytest.raises(ServerUnreachable):
        box.deliver(send)
    assert sent == [1, 2]
    again = Outbox(box.path)  # as a later process reads it
    assert [b.seq for b in again.read()] == [3, 4]
    assert [b.seq for b in again.deliver(lambda b: None)] == [3, 4] and not box.path.exists()


def test_a_line_a_crash_cut_short_is_skipped_and_does_not_swallow_the_next(tmp_path):
    box = Outbox(tmp_path / "outbox.jsonl")
    box.add("run", [("m", 1.0, 1000, 0)])
    with open(box.path, "a") as handle:
        handle.write('{"seq": 2, "run": "run", "metr')  # the process died here
    later = Outbox(box.path)
    assert [b.seq for b in later.read()] == [1]
    later.add("run", [("m", 2.0, 1001, 1)])
    assert [(b.seq, b.metrics[0][1]) for b in Outbox(box.path).read()] == [(1, 1.0), (2, 2.0)]


def test_a_batch_sent_again_after_a_crash_before_its_mark_adds_no_row_twice(tracker, tmp_path):
    run_id = new_run(tracker)
    box = Outbox(tmp_path / "outbox.jsonl")
    for step in range(3):
        box.add(run_id, [("val/loss", 1.0 / (step + 1), 1_700_000_000_000 + step, step)])
    tracker.send(box.read()[0])  # delivered, then the process died before marking it
    tracker.send(box.read()[1])
    assert [b.seq for b in Outbox(box.path).read()] == [1, 2, 3]  # no mark: all three are sent again
    Outbox(box.path).deliver(tracker.send)
    rows = history(tracker, run_id, "val/loss")
    assert [s for s, _, _ in rows] == [0, 1, 2] and len(set(rows)) == 3


def test_the_logger_keeps_training_while_the_server_is_down_and_delivers_each_value_once(
    tracker, tmp_path, monkeypatch, caplog
):
    monkeypatch.setattr(retry_module, "backoff", lambda attempt, cap=5.0: 0.0)
    monkeypatch.setattr(logger_module, "backoff", lambda attempt, cap=5.0: 0.0)
    run_id = new_run(tracker)
    down = Down(tracker, monkeypatch)
    logger = RunLogger(tracker, run_id, Outbox(tmp_path / "outbox.jsonl"))
    for step in range(10):
        down.down = 3 <= step < 7  # the server stops before step 3 and answers again at step 7
        calls = down.calls
        logger.log_metrics({"train/loss": 10.0 - step, "epoch": float(step // 5)}, step=step)
        if 3 <= step < 7:  # never waits for the server while it is down (step 7 delivers the backlog at once):
            # its own send and one try of the outbox at most, no retry loop (the backoff is 0 here: a wall-clock bound
            # could not tell)
            assert down.calls - calls <= 2
            assert logger.outbox.pending == step - 2
    assert not logger.outbox.path.exists()  # delivered at step 7 in order, step 7's own values last
    assert "training went on, and the 10 metric value(s) logged meanwhile are delivered" in caplog.text
    logger.deliver()
    assert [s for s, _, _ in history(tracker, run_id, "train/loss")] == list(range(10))
    assert len(history(tracker, run_id, "epoch")) == 10


def test_at_the_end_the_logger_waits_for_the_server_up_to_the_budget(tracker, tmp_path, monkeypatch):
    run_id = new_run(tracker)
    down = Down(tracker, monkeypatch)
    logger = RunLogger(tracker, run_id, Outbox(tmp_path / "outbox.jsonl"))
    down.down = True
    logger.log_metrics({"val/loss": 0.5}, step=4)
    assert logger.outbox.pending == 1
    start = time.monotonic()
    with pytest.raises(ServerUnreachable, match=r"did not answer for 2 s \(connection refused; logger.outage_s=2"):
        logger.deliver()  # tracker.outage_s = 2
    assert 2.0 <= time.monotonic() - start < 4.0 and logger.outbox.pending == 1
    down.down = False
    logger.deliver()
    assert [s for s, _, _ in history(tracker, run_id, "val/loss")] == [4] and not logger.outbox.path.exists()


def test_retry_waits_for_a_server_that_comes_back_and_names_one_that_does_not(caplog):
    calls = []

    def back_on_third():
        calls.append(time.monotonic())
        if len(calls) < 3:
            raise requests.exceptions.ConnectionError("Connection refused")
        return "ok"

    assert retry(back_on_third, outage_s=30, server="http://h:5000") == "ok" and len(calls) == 3
    assert "answers again after" in caplog.text

    def never():
        raise MlflowException(
            "API request to http://127.0.0.1:5999/api/2.0/mlflow/runs/log-batch failed with exception "
            "HTTPConnectionPool(host='127.0.0.1', port=5999): Max retries exceeded with url: /api/2.0/mlflow/runs/"
            "log-batch (Caused by ResponseError('too many 503 error responses'))"
        )

    def missing():
        raise MlflowException("RESOURCE_DOES_NOT_EXIST: no run")

    with pytest.raises(ServerUnreachable) as err:
        retry(never, outage_s=1)
    assert str(err.value).startswith("the tracking server http://127.0.0.1:5999 did not answer for 1 s (HTTP 503")
    assert "\n" not in str(err.value)
    with pytest.raises(MlflowException, match="RESOURCE_DOES_NOT_EXIST"):  # other errors at once
        retry(missing, outage_s=30)


def test_what_counts_as_a_server_that_does_not_answer():
    assert symptom(MlflowException(REFUSED)) == "connection refused"
    assert symptom(requests.exceptions.ConnectTimeout("x")) == "connection error"
    assert symptom(MlflowException("API request to http://h failed with timeout exception x")) == "timed out"
    broken = "('Connection broken: IncompleteRead(0 bytes read, 2 more expected)', IncompleteRead(0 bytes read))"
    # a server killed while it sent its answer (the request may have been stored: the outbox sends it again)
    assert symptom(MlflowException(f"API request to http://h/api/2.0/mlflow/runs/log-batch failed {broken}")) == (
        "connection dropped"
    )
    assert symptom(requests.exceptions.ChunkedEncodingError("x")) == "connection error"
    assert symptom(MlflowException("INVALID_PARAMETER_VALUE: bad metric")) is None
    assert symptom(MlflowException("API request failed with error code 401 != 200")) is None
    assert shown("postgresql://ablate:secret@127.0.0.1:5433/mlflow") == "postgresql://127.0.0.1:5433/mlflow"
    with socket.socket() as sock:  # a port nobody listens on: the health check says no at once
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    start = time.monotonic()
    assert not logger_module.answers(f"http://127.0.0.1:{port}")
    assert time.monotonic() - start < 3


def test_a_run_whose_end_the_server_did_not_take_is_ended_by_the_next_job(tracker, tmp_path, monkeypatch):
    run_id = new_run(tracker)
    down = Down(tracker, monkeypatch)
    box = Outbox(tmp_path / "ckpt" / "outbox.jsonl")
    logger = RunLogger(tracker, run_id, box)
    down.down = True
    logger.log_metrics({"val/loss": 0.5}, step=3)
    try:
        logger.deliver()
    except ServerUnreachable as err:
        message = kept_for_later(box, run_id, tmp_path / "ckpt", str(err))
    assert unreachable(RuntimeError("x")) is None
    assert f"run {run_id} stays RUNNING" in message and "its end (FAILED) and 1 metric value(s) wait in" in message
    assert "(no checkpoint was written yet)" in message
    assert tracker.get_run(run_id).info.status == "RUNNING"
    down.down = False
    deliver_earlier(tracker, Outbox(box.path))  # the next job of the same config
    run = tracker.get_run(run_id)
    assert run.info.status == "FAILED" and "did not answer for 2 s" in run.data.tags["error"]
    assert run.data.metrics["val/loss"] == 0.5 and not box.path.exists()


def test_a_stopped_job_whose_server_is_down_keeps_its_end_for_the_next(tracker, tmp_path, monkeypatch):
    run_id = new_run(tracker)
    down = Down(tracker, monkeypatch)
    box = Outbox(tmp_path / "outbox.jsonl")
    down.down = True
    RunLogger(tracker, run_id, box).log_metrics({"m": 1.0}, step=0)
    record_end(tracker, run_id, "KILLED", {"killed_by": "SIGTERM"}, outbox=box)  # no waiting: the outbox is full
    pending = Outbox(box.path).read()
    assert [b.status for b in pending] == [None, "KILLED"] and pending[1].tags == {"killed_by": "SIGTERM"}
    down.down = False
    deliver_earlier(tracker, Outbox(box.path))
    run = tracker.get_run(run_id)
    assert run.info.status == "KILLED" and run.data.tags["killed_by"] == "SIGTERM" and run.data.metrics["m"] == 1.0


def test_an_outbox_the_server_refuses_is_moved_aside_by_name(tracker, tmp_path, caplog):
    box = Outbox(tmp_path / "outbox.jsonl")
    box.add("no-such-run", [("m", 1.0, 1000, 0)])
    deliver_earlier(tracker, box)
    aside = tmp_path / "outbox.jsonl.undelivered"
    assert aside.exists() and not box.path.exists() and str(aside) in caplog.text
    assert json.loads(aside.read_text().splitlines()[0])["run"] == "no-such-run"


def test_a_tracker_pickles_with_its_budget(tracker):
    import pickle

    assert pickle.loads(pickle.dumps(tracker)).outage_s == 2
