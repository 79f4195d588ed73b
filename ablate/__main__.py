"""`python -m ablate [-m] key=value ...`: run one job, or a Hydra multirun sweep of jobs."""

import hydra
from omegaconf import DictConfig

from ablate.run.job import main as run_job


@hydra.main(version_base="1.3", config_path="../conf", config_name="config")
def main(cfg: DictConfig) -> str:
    return run_job(cfg)


if __name__ == "__main__":
    main()
