"""The orchestration: one job (:mod:`~ablate.run.job`), two-stage experts (:mod:`~ablate.run.experts`), the sweep
callback and its progress (:mod:`~ablate.run.sweep`, :mod:`~ablate.run.progress`), side-by-side latency
(:mod:`~ablate.run.latency`), the job's fingerprint (:mod:`~ablate.run.fingerprint`) and the diagnosis
(:mod:`~ablate.run.diagnose`). It imports the store and the tables; nothing below imports it."""
