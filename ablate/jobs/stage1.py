"""What the job running in this process spent on stage 1 (SMoE §4.3: the experts it starts from, trained first
where missing, :func:`ablate.jobs.job.prepare_experts`), for the sweep's progress ETA (:mod:`ablate.sweep.progress`).

A raced job that trains an expert takes the expert's training too; the jobs after it, whose experts are trained, do
not. The progress line times the two apart: each expert trained at the trained experts' mean, each job at its own
time less its stage 1. A process runs one job at a time (Hydra's launchers run a job per process or worker), so the
record is this process's; the sweep's callback clears it as each job starts and reads it as the job ends.
"""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass
class StageOne:
    """The current job's stage 1: the seconds of each expert it trained, and its seconds in stage 1 in all
    (training, waiting for an expert another job trains, copying or loading a trained one)."""

    trained: list[float] = field(default_factory=list)
    seconds: float = 0.0

    def clear(self) -> None:
        self.trained.clear()
        self.seconds = 0.0


#: This process's current job's stage 1.
CURRENT = StageOne()
