"""Where a job or a command runs: the launch directory and, in a multirun, its sweep (the store its jobs log to,
their parent run, the keys it sweeps over), read once where the job or command starts (:meth:`SweepContext.current`)
and passed down. Below that point nothing reads Hydra's globals or the sweep directory's files.

A multirun records its store, its parent run and the keys it sweeps in its sweep directory's state file
(:data:`STATE_FILE`: ``store``, ``parent_run``, ``swept``), which every launcher's jobs see: the basic one, joblib,
submitit (local or SLURM, on a shared filesystem) and Ray (the sweep directory is absolute, under the launch
directory). A job so writes to its parent's store even where its own environment names no store (a Ray worker does
not inherit the driver's ``MLFLOW_TRACKING_URI``). The racing sweeper writes the file (:mod:`ablate.sweep.state`);
this module names it and reads it, so the store never imports the orchestration.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from pathlib import Path

from ablate.store.identity import row_name

#: A sweep's state file in its sweep directory (:mod:`ablate.sweep.state`, which writes it).
STATE_FILE = "sweep.json"
FAILURES = "failures"


@dataclass(frozen=True)
class SweepContext:
    """What a job or command knows of where it runs.

    ``launch_dir``: the directory the command was started in (Hydra's ``hydra.runtime.cwd``; relative stores, data
    and checkpoints resolve against it). ``sweep_dir``: the multirun's sweep directory, None for a single run.
    ``job_num``: the job's number in its sweep. ``overrides``: the job's own command-line overrides. ``row_choice``:
    the config's ``row`` choice. ``store``: the store the sweep recorded (``uri``, ``artifact_location``).
    ``parent_run``: the sweep's MLflow run. ``swept``: the keys the sweep sweeps over (None: not recorded).
    ``output_dir``: the job's own output folder (its log, Hydra's ``.hydra/``), None outside a Hydra job.
    """

    launch_dir: Path
    sweep_dir: Path | None = None
    job_num: int | None = None
    overrides: tuple[str, ...] = ()
    row_choice: str | None = None
    store: dict[str, str | None] | None = None
    parent_run: str | None = None
    swept: tuple[str, ...] | None = None
    output_dir: Path | None = None

    @classmethod
    def current(cls) -> SweepContext:
        """The context of the running Hydra job (the current directory's, outside one): Hydra's config and the
        sweep directory's files, read here and only here."""
        from hydra.core.hydra_config import HydraConfig
        from omegaconf.errors import MissingMandatoryValue

        if not HydraConfig.initialized():
            return cls(Path.cwd())
        hc = HydraConfig.get()
        launch = Path(str(hc.runtime.cwd))
        multirun = hc.mode is not None and hc.mode.name == "MULTIRUN"
        sdir = launch / str(hc.sweep.dir) if multirun else None
        choice = hc.runtime.choices.get("row")
        try:
            num: int | None = int(hc.job.num)
        except MissingMandatoryValue:  # a single run has no job number
            num = None
        overrides = tuple(str(o) for o in hc.overrides.task)
        job = cls.of_sweep(sdir, launch).with_job(num, overrides, str(choice) if choice else None)
        try:
            output: Path | None = Path(str(hc.runtime.output_dir))
        except MissingMandatoryValue:  # a config composed outside a running job
            output = None
        return dataclasses.replace(job, output_dir=output)

    @classmethod
    def of_sweep(cls, sweep_dir: Path | None, launch_dir: Path) -> SweepContext:
        """The context a sweep directory's state file holds (:data:`STATE_FILE`; none before the sweeper wrote it)."""
        path = sweep_dir / STATE_FILE if sweep_dir is not None else None
        state = json.loads(path.read_text()) if path is not None and path.exists() else {}
        swept = state.get("swept")
        return cls(
            launch_dir=launch_dir,
            sweep_dir=sweep_dir,
            store=state.get("store"),
            parent_run=state.get("parent_run"),
            swept=tuple(swept) if swept is not None else None,
        )

    def with_job(self, num: int | None, overrides: tuple[str, ...], row_choice: str | None) -> SweepContext:
        """This context for one job of the sweep."""
        return SweepContext(
            self.launch_dir, self.sweep_dir, num, overrides, row_choice, self.store, self.parent_run, self.swept
        )

    def record_failure(self, message: str) -> None:
        """Leave a note that this job failed (``<job number>_<row>``), for the end-of-sweep summary (nothing outside
        a multirun)."""
        if self.sweep_dir is not None:
            row = row_name(self.overrides, self.swept, self.row_choice)
            job = f"{self.job_num}_{row.replace(' ', '_').replace('/', '-')}"
            (self.sweep_dir / FAILURES).mkdir(parents=True, exist_ok=True)
            (self.sweep_dir / FAILURES / f"{job}.txt").write_text(message)

    def failures(self) -> list[Path]:
        """The notes of the sweep's failed jobs."""
        folder = self.sweep_dir / FAILURES if self.sweep_dir is not None else None
        return sorted(folder.glob("*.txt")) if folder is not None and folder.is_dir() else []
