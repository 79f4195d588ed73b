"""The libraries' remarks a job expects, silenced: each is about a use this project makes on purpose, and printed
once per job process they would fill a table's sweep log.

:func:`silence` installs them where a job starts (:mod:`ablate.jobs.job`) and where a task module is imported
(:mod:`ablate.tasks.base`). A module-level filter alone is not enough: a module first imported inside
``warnings.catch_warnings()`` (the fingerprint instantiates the task in one) loses its filter when that block ends.
"""

from __future__ import annotations

import warnings

#: (message pattern, why it is expected) of each silenced warning.
KNOWN: tuple[tuple[str, str], ...] = (
    (".*does not have many workers.*", "the cpu scale loads in the job's own process (data.num_workers: 0)"),
    (".*GPU available but not used.*", "a job runs where its config says (trainer.accelerator)"),
    (
        ".*overridden `on_before_batch_transfer` in `LightningModule`.*",
        "the training corruptions are applied in the task's batch hook whatever the data module",
    ),
    (
        r".*isinstance\(treespec, LeafSpec\)` is deprecated.*",
        "Lightning's own pytree helper on torch 2.13, nothing this project calls",
    ),
    (
        ".*The dirpath has changed from.*",
        "a single-modal row tests its expert's checkpoint, kept in the expert's folder; testing reads no callback state",
    ),
)


def silence() -> None:
    """Ignore every warning of :data:`KNOWN` in this process (idempotent: a filter already present moves to the front,
    never listed twice)."""
    for pattern, _ in KNOWN:
        warnings.filterwarnings("ignore", pattern)
