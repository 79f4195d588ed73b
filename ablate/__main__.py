"""`python -m ablate [-m] key=value ...`: run one job, or a Hydra multirun sweep of jobs."""

import hydra
from omegaconf import DictConfig

import ablate.run  # noqa: F401 (its warning filter, before Hydra composes)


@hydra.main(version_base="1.3", config_path="../conf", config_name="config")
def main(cfg: DictConfig) -> str:
    from ablate.run.job import main as run_job  # torch and Lightning: imported once a job runs, not for a bad option

    return run_job(cfg)


if __name__ == "__main__":
    main()
