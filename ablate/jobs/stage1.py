"""What a job spent on stage 1 (SMoE §4.3: the experts it starts from, trained first where missing,
:func:`ablate.jobs.job.prepare_experts`), for the sweep's progress ETA (:mod:`ablate.sweep.progress`).

A raced job that trains an expert takes the expert's training too; the jobs after it, whose experts are trained, do
not. The progress line times the two apart: each expert trained at the trained experts' mean of its modality, each
job at its own time less its stage 1. The job returns its record with its status (:class:`Ended`, Hydra's
``JobReturn`` carries it to the sweep's callback and, pickled, back from a launcher's worker): nothing of a job
outlives it in its process.
"""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass
class StageOne:
    """A job's stage 1: the seconds of each expert it trained, by modality, and its seconds in stage 1 in all
    (training, waiting for an expert another job trains, copying or loading a trained one)."""

    trained: dict[str, float] = field(default_factory=dict)
    seconds: float = 0.0


class Ended(str):
    """A job's status as its task function returns it (``FINISHED``, ``SKIPPED``, ``FAILED``, ...: it compares as
    that string), with the job's :class:`StageOne` (``stage1``)."""

    stage1: StageOne

    def __new__(cls, status: str, stage1: StageOne | None = None) -> Ended:
        ended = super().__new__(cls, status)
        ended.stage1 = stage1 if stage1 is not None else StageOne()
        return ended

    def __reduce__(self) -> tuple[type[Ended], tuple[str, StageOne]]:
        return (Ended, (str(self), self.stage1))
