"""Running one job: its spec (:mod:`~ablate.jobs.spec`: table, row, seed, config hash, checkpoint directory, the
sweep it belongs to), the job itself (:mod:`~ablate.jobs.job`), its run's params and tags (:mod:`~ablate.jobs.tags`),
a job the store already holds, skipped or copied (:mod:`~ablate.jobs.reuse`), two-stage experts
(:mod:`~ablate.jobs.experts`), checkpoints (:mod:`~ablate.jobs.checkpoint`), preemption (:mod:`~ablate.jobs.preempt`),
how its run ends (:mod:`~ablate.jobs.record`) and its fingerprint (:mod:`~ablate.jobs.fingerprint`). It imports the
store and the tables; the analysis, the sweep and the capacity planning import it."""
