"""The orchestration: one job (:mod:`~ablate.run.job`), two-stage experts (:mod:`~ablate.run.experts`), the sweep
callback and its progress (:mod:`~ablate.run.sweep`, :mod:`~ablate.run.progress`), side-by-side latency
(:mod:`~ablate.run.latency`), the job's fingerprint (:mod:`~ablate.run.fingerprint`) and the diagnosis
(:mod:`~ablate.run.diagnose`). It imports the store and the tables; nothing below imports it."""

import warnings

# conf/hydra/launcher/ray.yaml and submitit_local.yaml replace the plugins' configs of the same names, holding
# exactly their keys. Hydra 1.3 still validates a file against a ConfigStore entry of the same name and warns that
# this "automatic schema matching" is deprecated
# (https://hydra.cc/docs/1.2/upgrades/1.0_to_1.1/automatic_schema_matching); the files compose the same with or
# without it, so the warning tells a user nothing. ``python -m ablate`` imports this package before Hydra composes,
# in the launching process and in every submitit job.
warnings.filterwarnings("ignore", message=r"\s*'hydra/launcher/(ray|submitit_local)' is validated against ConfigStore")
