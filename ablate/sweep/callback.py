"""A Hydra callback that reports each job's end to its sweep: the job's outcome and time added to the sweep's state
file, and the sweep's progress line with its ETA (:mod:`ablate.sweep.progress`).

Hydra calls it in whichever process runs the job (the sweep's own with the basic launcher, a worker's with joblib,
submitit or Ray). Everything else of a sweep's life (its parent run, its plan, its phases, its table) belongs to the
racing sweeper (``hydra_plugins/ablate_racing_sweeper``).
"""

from __future__ import annotations

import logging
import time
from typing import Any

from hydra.experimental.callback import Callback
from omegaconf import DictConfig

from ablate.jobs import stage1
from ablate.store import SweepContext
from ablate.sweep import progress

log = logging.getLogger(__name__)


class SweepCallback(Callback):
    """Times each job of a sweep and reports its end."""

    def on_job_start(self, config: DictConfig, **kwargs: Any) -> None:
        self._job_started = time.monotonic()

    def on_job_end(self, config: DictConfig, job_return: Any, **kwargs: Any) -> None:
        """Count the job in the sweep's progress and log the sweep's progress line with its ETA."""
        sdir = SweepContext.current().sweep_dir
        if sdir is None or not hasattr(self, "_job_started"):
            return
        status = job_return._return_value if job_return.status.name == "COMPLETED" else "FAILED"
        try:
            overrides, seconds = list(config.hydra.overrides.task), time.monotonic() - self._job_started
            row, trial = progress.job_row(overrides), progress.job_trial(overrides)
            kind = progress.job_kind(overrides)
            # what the job spent on its experts, returned with its status (ablate.jobs.stage1)
            ran = status.stage1 if isinstance(status, stage1.Ended) else stage1.StageOne()
            line = progress.finished(
                sdir, str(status), seconds, progress.workers(config), kind, row, trial, dict(ran.trained), ran.seconds
            )
            log.info(line)
        except Exception as err:  # any error of the sweep's bookkeeping: the job's own outcome stands as it ended
            log.warning("Could not record the sweep's progress: %s", err)
