"""Checkpoints that survive a dying node: written atomically, checked before a resume.

Every checkpoint Lightning writes (``ModelCheckpoint``'s ``best.ckpt`` and ``last.ckpt``, ``trainer.save_checkpoint``)
goes through the trainer's CheckpointIO plugin; :class:`AtomicCheckpointIO` writes the file under a temporary name
in the same folder (``.<name>.<pid>.<random>.tmp``), flushes and fsyncs it, and renames it into place with
:func:`os.replace`, so a process killed in the middle of a write leaves the previous checkpoint as it was.
Lightning's own TorchCheckpointIO writes through an fsspec transaction whose temporary file is in the system's
temporary folder, which ``shutil.move`` copies across filesystems: not atomic there. A full disk
(``ENOSPC``, ``EDQUOT``) is one :class:`~ablate.store.DiskFull` naming the checkpoint.

:func:`resume_point` picks what a rerun resumes from: ``last.ckpt`` if it loads, else ``best.ckpt``, else nothing
(training from scratch). A checkpoint that does not load (truncated, corrupt, not a Lightning checkpoint) is
moved aside to ``<name>.corrupt`` with one warning naming it, and the choice is recorded in the run's tags.
"""

from __future__ import annotations

import errno
import logging
import os
import uuid
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any

import torch
from lightning.fabric.plugins.io.torch_io import TorchCheckpointIO

from ablate.store import DiskFull

log = logging.getLogger(__name__)

#: What a full disk or an exceeded quota raises as.
FULL = (errno.ENOSPC, errno.EDQUOT)
#: What every Lightning training checkpoint holds; a file without them is not one to resume from.
KEYS = ("state_dict", "epoch", "global_step", "loops")


def temporary_name(path: Path) -> Path:
    """A name beside ``path`` no other process writes: hidden, with this process's id and a random part."""
    return path.with_name(f".{path.name}.{os.getpid()}.{uuid.uuid4().hex[:8]}.tmp")


def write_atomic(path: str | Path, write: Callable[[IO[bytes]], Any], what: str = "checkpoint") -> None:
    """Write ``path`` with ``write(file)`` to a temporary name in the same folder, fsync it, and rename it into
    place: ``path`` is either the old file or the new one, whole, whenever the process dies. The temporary file
    is removed on an error; a full disk raises :class:`DiskFull` naming ``path``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = temporary_name(path)
    try:
        with open(tmp, "wb") as handle:
            write(handle)
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp, path)
    except BaseException as err:
        tmp.unlink(missing_ok=True)
        if isinstance(err, OSError) and err.errno in FULL:
            raise DiskFull(
                f"no space left on the device writing the {what} {path} ({err.strerror}); the previous "
                f"{path.name}, if any, is kept"
            ) from err
        raise
    try:  # the rename itself reaches the disk with the folder's entry
        folder = os.open(path.parent, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(folder)
    except OSError:
        pass
    finally:
        os.close(folder)


class AtomicCheckpointIO(TorchCheckpointIO):
    """Lightning's CheckpointIO with :func:`write_atomic` for saving; loading and removal are Lightning's."""

    def save_checkpoint(self, checkpoint: dict[str, Any], path: Any, storage_options: Any | None = None) -> None:
        if storage_options is not None:
            raise TypeError(f"{type(self).__name__} takes no storage_options")
        write_atomic(path, lambda handle: torch.save(checkpoint, handle))


def load(path: Path) -> tuple[dict[str, Any] | None, str | None]:
    """``path``'s checkpoint and None, or None and why it cannot be resumed from (it does not load, or lacks a
    training checkpoint's keys)."""
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as err:
        return None, f"{type(err).__name__}: {str(err).splitlines()[0] if str(err) else 'unreadable'}"
    missing = [k for k in KEYS if not isinstance(ckpt, dict) or k not in ckpt]
    if missing:
        return None, f"not a Lightning training checkpoint: no {', '.join(missing)}"
    return ckpt, None


@dataclass
class Resume:
    """Where a job's training starts: ``path`` (None: from scratch), the run tags that record it, and the step
    and epoch it resumes at."""

    path: Path | None
    tags: dict[str, str]
    step: int = 0
    epoch: int = 0


def resume_point(ckpt_dir: Path) -> Resume:
    """What a job with checkpoints in ``ckpt_dir`` resumes from: ``last.ckpt``, else ``best.ckpt``, else nothing.

    Temporary files a killed write left are removed. A ``last.ckpt`` (or ``best.ckpt``) that does not load is
    renamed ``<name>.corrupt`` and named in one warning, which says what the job starts from instead; the tags
    (``resumed_from``: the checkpoint or ``scratch``; ``resumed_step``; ``checkpoint_unreadable``: the files and
    why) go to the run. A directory with neither file gives no tags: a fresh job."""
    ckpt_dir = Path(ckpt_dir)
    for tmp in ckpt_dir.glob(".*.ckpt.*.tmp") if ckpt_dir.is_dir() else []:
        log.info("Removing %s, left by a write that did not finish", tmp)
        tmp.unlink(missing_ok=True)
    bad: list[str] = []
    for name in ("last.ckpt", "best.ckpt"):
        path = ckpt_dir / name
        if not path.exists():
            continue
        ckpt, why = load(path)
        if ckpt is not None:
            step, epoch = int(ckpt.get("global_step", 0)), int(ckpt.get("epoch", 0))
            tags = {"resumed_from": str(path), "resumed_step": str(step)}
            if bad:
                log.warning("%s; resuming from %s (step %d)", "; ".join(bad), path, step)
                tags["checkpoint_unreadable"] = "; ".join(bad)
            return Resume(path, tags, step, epoch)
        os.replace(path, path.with_name(name + ".corrupt"))
        bad.append(f"checkpoint {path} is unreadable ({why}), moved to {path.name}.corrupt")
    if not bad:
        return Resume(None, {})
    log.warning("%s; training from scratch", "; ".join(bad))
    return Resume(None, {"resumed_from": "scratch", "resumed_step": "0", "checkpoint_unreadable": "; ".join(bad)})
