"""`python -m ablate [-m] key=value ...`: run one job, or a Hydra multirun sweep of jobs."""

import os
import sys
import warnings
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import DictConfig

from ablate.options import OptionError, check

# conf/hydra/launcher/ray.yaml and submitit_local.yaml replace the plugins' configs of the same names, holding
# exactly their keys. Hydra 1.3 still validates a file against a ConfigStore entry of the same name and warns that
# this "automatic schema matching" is deprecated
# (https://hydra.cc/docs/1.2/upgrades/1.0_to_1.1/automatic_schema_matching); the files compose the same with or
# without it, so the warning tells a user nothing. Set here, before Hydra composes, in the launching process and in
# every submitit job (which imports this module to find its task function).
warnings.filterwarnings("ignore", message=r"\s*'hydra/launcher/(ray|submitit_local)' is validated against ConfigStore")
# A parallel sweep's loky worker whose memory grew by more than 300 MB over its jobs (loky's _MAX_MEMORY_LEAK_SIZE;
# BiFNet's expert feature cache alone is 406 MiB) retires after its job has returned, and loky starts another in its
# place for the next job, warning in the sweep's process that "a worker stopped" and naming a memory leak: nothing is
# lost or rerun (seen in `make run`). A worker that dies in a job fails that job through loky's own error instead.
warnings.filterwarnings("ignore", message="A worker stopped while some jobs were given to the executor")


#: The configs, by absolute path: `python -m ablate` and the `ablate` console script (where Hydra would otherwise look
#: for a Python package ablate.conf) find them alike, in a checkout and in an installed wheel.
CONFIGS = str(Path(__file__).resolve().parent / "conf")


@hydra.main(version_base="1.3", config_path=CONFIGS, config_name="config")
def main(cfg: DictConfig) -> str:
    """One job: its options checked first (:mod:`ablate.options`), before it imports torch or opens the store."""
    try:
        check(cfg, Path(HydraConfig.get().runtime.cwd))
    except OptionError as err:
        return refused(err)
    from ablate.jobs.job import main as run_job  # torch and Lightning: imported once a job runs, not for a bad option

    return run_job(cfg)


def refused(err: OptionError) -> str:
    """A job whose option is refused, before any run: one line and status 1; in a sweep, a note for the sweep's
    summary, as a job that fails leaves (``ablate.jobs.job.main``), and the other jobs go on."""
    if HydraConfig.get().mode != RunMode.MULTIRUN:
        print(f"error: {err}", file=sys.stderr)
        raise SystemExit(1)
    from ablate.store import SweepContext  # MLflow: a sweep's job has it loaded already

    SweepContext.current().record_failure(str(err))
    return "FAILED"


def script() -> None:
    """The ``ablate`` console script: :func:`main` with the folder it runs in first on ``sys.path``, as
    ``python -m ablate`` has it, so that a ``_target_`` naming a user's own module there (``my_ops.Product``) is found
    by either command."""
    here = os.getcwd()
    if here not in sys.path and "" not in sys.path:
        sys.path.insert(0, here)
    main()


if __name__ == "__main__":
    main()
