"""Preemption: a job stopped by SIGTERM (SLURM's preemption signal, submitit's) or SIGINT saves a checkpoint, is
recorded KILLED with the reason, and exits; its rerun resumes from that checkpoint.

While a job runs, :class:`Stop` holds SIGTERM and SIGINT. Inside a Lightning trainer the signal only raises
Lightning's own flag (``trainer.received_sigterm``, which its SignalConnector sets for SIGTERM and this sets for
SIGINT too): the loops end after the batch in progress, and :class:`SaveOnStop` writes ``last.ckpt`` with the loops'
state, so the rerun goes on from the next batch. Outside a trainer (data generation, the fingerprint, logging) the
signal raises :class:`Stopped` at once: nothing trained is lost there. A repeated signal changes nothing.

A sweep's parent (``hydra/launcher=parallel`` or ``joblib``: loky worker processes) on SIGTERM or SIGINT passes
SIGTERM on to its workers (:func:`stop_workers`), whose jobs stop as above and whose processes then exit; it waits
for them (``GRACE_S``), kills any still there, and exits itself.
"""

from __future__ import annotations

import logging
import os
import signal
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from types import FrameType
from typing import Any

import lightning as L
from lightning.pytorch.callbacks import Callback
from lightning.pytorch.utilities.exceptions import SIGTERMException

log = logging.getLogger(__name__)

SIGNALS = (signal.SIGTERM, signal.SIGINT)
#: Seconds a sweep's parent waits for its workers to checkpoint and exit before it kills them.
GRACE_S = 60.0
#: Seconds a sweep's worker waits after recording its stop, before it exits: loky kills a pool's other workers as
#: soon as one exits, and both got SIGTERM at once, so a slower sibling may still be recording its KILLED status.
SETTLE_S = 3.0


class Stopped(BaseException):
    """The job was stopped by a signal (a BaseException, as KeyboardInterrupt: ``except Exception`` lets it by)."""

    def __init__(self, signame: str) -> None:
        super().__init__(signame)
        self.signame = signame
        #: the checkpoint saved on the way out and its step, if the job was training
        self.checkpoint: tuple[Path, int] | None = None
        #: what the run's ``kill_reason`` tag says
        self.reason = f"stopped by {signame}"


def exit_status(signame: str) -> int:
    """The shell's status for a process ended by ``signame``: 128 + its number (143 for SIGTERM)."""
    return 128 + int(getattr(signal, signame, signal.SIGTERM))


class Stop:
    """The job's handler of SIGTERM and SIGINT, installed by :meth:`installed` for the job's lifetime."""

    def __init__(self) -> None:
        self.signame: str | None = None
        self.trainer: L.Trainer | None = None
        self.raised = False
        self.depth = 0

    def handle(self, signum: int, frame: FrameType | None) -> None:
        first = self.signame is None
        self.signame = self.signame or signal.Signals(signum).name
        if not first:
            return
        log.warning("Received %s: stopping the job (a checkpoint is saved if it is training)", self.signame)
        if self.trainer is not None:
            connector = getattr(self.trainer, "_signal_connector", None)
            if connector is not None:  # Lightning's own flag: its loops end after the batch in progress
                connector.received_sigterm = True
        else:
            self.check()

    def check(self) -> None:
        """Raise :class:`Stopped` if a signal came and has not been raised yet."""
        if self.signame is not None and not self.raised:
            self.raised = True
            raise Stopped(self.signame)

    @contextmanager
    def installed(self) -> Iterator[Stop]:
        """Hold SIGTERM and SIGINT for the block (main thread only), then give the previous handlers back. A block
        inside another (an expert's job inside a fused job) changes nothing."""
        import threading

        if self.depth:
            yield self
            return
        self.signame, self.trainer, self.raised = None, None, False
        if threading.current_thread() is not threading.main_thread():
            yield self
            return
        previous = {s: signal.getsignal(s) for s in SIGNALS}
        for s in SIGNALS:
            signal.signal(s, self.handle)
        self.depth += 1
        try:
            yield self
        finally:
            self.depth -= 1
            for s, handler in previous.items():
                signal.signal(s, handler if handler is not None else signal.SIG_DFL)

    @contextmanager
    def training(self, trainer: L.Trainer) -> Iterator[None]:
        """Around ``trainer.fit`` / ``trainer.test``: a signal lets the batch in progress finish; a
        :class:`SIGTERMException` out of the trainer becomes :class:`Stopped`."""
        self.check()
        self.trainer = trainer
        try:
            yield
        except SIGTERMException as err:
            self.raised = True
            raise Stopped(self.signame or "SIGTERM") from err
        finally:
            self.trainer = None
        if getattr(trainer, "received_sigterm", False) and self.signame is None:
            self.signame = "SIGTERM"  # Lightning's handler saw it, ours was not installed (not the main thread)
        self.check()


#: The job's :class:`Stop`, one per process (a job's experts run inside it).
STOP = Stop()


class SaveOnStop(Callback):
    """On a stop signal in the middle of ``fit``, save ``path`` (the job's ``last.ckpt``) with the loops' state
    after the last finished batch."""

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        self.saved_step: int | None = None

    def on_exception(self, trainer: L.Trainer, pl_module: L.LightningModule, exception: BaseException) -> None:
        if not isinstance(exception, SIGTERMException) or trainer.state.fn != "fit":
            return
        trainer.save_checkpoint(self.path)
        self.saved_step = trainer.global_step
        log.warning("Saved %s at step %d (epoch %d)", self.path, trainer.global_step, trainer.current_epoch)


def loky_worker() -> bool:
    """Whether this process is a loky worker (``hydra/launcher=joblib`` or ``parallel``)."""
    import multiprocessing

    return multiprocessing.current_process().name.startswith("LokyProcess")


def _children() -> list[int]:
    """This process's loky workers: the reusable executor's processes, else every child in /proc whose command
    line names loky, but its resource tracker."""
    pids: set[int] = set()
    try:
        from joblib.externals.loky import reusable_executor

        executor = getattr(reusable_executor, "_executor", None)
        pids |= set(getattr(executor, "_processes", None) or {})
    except ImportError:
        pass
    me = str(os.getpid())
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
            cmdline = (stat.parent / "cmdline").read_bytes().replace(b"\0", b" ")
        except (OSError, IndexError):
            continue
        if fields[1] == me and b"loky" in cmdline and b"resource_tracker" not in cmdline:
            pids.add(int(stat.parent.name))
    return sorted(pids)


def alive(pid: int) -> bool:
    """Whether process ``pid`` exists (one of another user counts; a zombie child of ours is reaped, and does not)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    try:  # a zombie of ours: reap it
        done, _ = os.waitpid(pid, os.WNOHANG)
        return done == 0
    except ChildProcessError:
        return True


def stop_workers(grace_s: float = GRACE_S) -> tuple[int, int]:
    """Send SIGTERM to this process's loky workers, wait up to ``grace_s`` for them to exit, SIGKILL those left.
    Returns (workers stopped, workers killed)."""
    pids = _children()
    for pid in pids:
        try:
            os.kill(pid, signal.SIGTERM)
        except ProcessLookupError:
            pass
    deadline = time.monotonic() + grace_s
    while time.monotonic() < deadline and any(alive(p) for p in pids):
        time.sleep(0.1)
    killed = [p for p in pids if alive(p)]
    for pid in killed:
        try:
            os.kill(pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
    return len(pids), len(killed)


def install_parent(on_stop: Any) -> None:
    """In a sweep's parent: on SIGTERM or SIGINT, stop the workers (:func:`stop_workers`), call
    ``on_stop(signame, stopped, killed)``, and exit with 128 + the signal's number. Main thread only."""
    import threading

    if threading.current_thread() is not threading.main_thread():
        return

    def handle(signum: int, frame: FrameType | None) -> None:
        for s in SIGNALS:
            signal.signal(s, signal.SIG_IGN)
        name = signal.Signals(signum).name
        log.warning("Received %s: stopping the sweep's workers (each saves its job's checkpoint)", name)
        stopped, killed = stop_workers()
        try:
            on_stop(name, stopped, killed)
        finally:
            logging.shutdown()
            os._exit(exit_status(name))

    for s in SIGNALS:
        signal.signal(s, handle)
