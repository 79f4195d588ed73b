"""Where the output is not a terminal, a job's progress is a line a person can read, not a progress bar's carriage
returns: a redirected sweep's log stays small and shows every job's end."""

from __future__ import annotations

import logging
from pathlib import Path
from types import SimpleNamespace

import pytest

from ablate.jobs.progress_lines import ProgressLines, progress_bar
from tests.scaleout import SERIAL, ablate, output


def test_the_bar_shows_on_a_terminal_only_unless_told() -> None:
    assert progress_bar("auto", tty=lambda: True) is True and progress_bar("auto", tty=lambda: False) is False
    assert progress_bar(True, tty=lambda: False) is True and progress_bar(False, tty=lambda: True) is False
    with pytest.raises(ValueError, match="trainer.enable_progress_bar='sometimes'"):
        progress_bar("sometimes")


def test_a_line_every_period_with_the_time_left_from_the_steps_done(caplog: pytest.LogCaptureFixture) -> None:
    clock = [0.0]
    lines = ProgressLines(every_s=30.0, clock=lambda: clock[0])
    trainer = SimpleNamespace(
        global_step=0, estimated_stepping_batches=100, current_epoch=0, max_epochs=4, callback_metrics={}
    )
    caplog.set_level(logging.INFO, logger="ablate.jobs.progress_lines")
    lines.on_train_start(trainer, None)  # type: ignore[arg-type]
    for step in range(1, 41):  # a step every 1.5 s: a line at 30 s and at 60 s, none between
        clock[0], trainer.global_step = 1.5 * step, step
        trainer.callback_metrics = {"train/loss": 2.0 / step}
        lines.on_train_batch_end(trainer, None, None, None, step)  # type: ignore[arg-type]
    said = [r.getMessage() for r in caplog.records]
    assert said == [
        "epoch 1/4, step 20/100, loss 0.1, about 2.0 min left",  # 30 s for 20 steps: 80 more take 120 s
        "epoch 1/4, step 40/100, loss 0.05, about 1.5 min left",
    ]


def test_a_redirected_sweeps_log_has_no_progress_bar_and_every_jobs_end(tmp_path: Path) -> None:
    # the output is a pipe, as a log file: enable_progress_bar is left at its default (auto)
    tiny = ["scale=smoke", "data.synth.frames=20", "comp_time.repeats=2", "trainer.max_epochs=2", "plan.measure_s=30"]
    tiny.append("logger.log_figures=false")
    out = ablate(tmp_path, "-m", "task=semantic", "model=unet,fusenet", *tiny, SERIAL)
    assert out.returncode == 0, output(out)
    text = out.stdout + out.stderr
    assert "\r" not in text  # no progress-bar refresh
    assert text.count("FINISHED model=") == 2 and "epoch 2/2, step" in text
    # the plan and its ETA before the first job ends
    assert -1 < text.find("Sweep plan: 2 job(s), 1 at a time") < text.find("Sweep ETA: ~") < text.find("FINISHED")
    assert len(text.encode()) < 20_000, f"{len(text.encode())} bytes for 2 jobs of 2 epochs"
