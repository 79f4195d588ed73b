"""The libraries' remarks a job expects stay out of its log, in a process as a job runs it (ablate.tasks.quiet)."""

import subprocess
import sys

from tests.scaleout import REPO

# A job process: the job module first, then the task module, first imported inside warnings.catch_warnings() as the
# fingerprint imports it; then the libraries' real remarks, and one warning of another kind.
JOB_PROCESS = r"""
import warnings
import ablate.jobs.job
with warnings.catch_warnings():
    import ablate.tasks.base
from lightning.pytorch.callbacks import ModelCheckpoint
from lightning.pytorch.utilities import rank_zero_warn
from lightning.pytorch.utilities._pytree import _tree_flatten
_tree_flatten(1.0)
ModelCheckpoint(dirpath="/a/row").load_state_dict({"dirpath": "/its/expert", "best_model_path": ""})
rank_zero_warn(
    "You have overridden `on_before_batch_transfer` in `LightningModule` but have passed in a `LightningDataModule`."
)
warnings.warn("a remark nobody expected")
"""


def test_a_jobs_expected_remarks_are_silent_and_other_warnings_still_speak():
    out = subprocess.run(
        [sys.executable, "-c", JOB_PROCESS], capture_output=True, text=True, cwd=REPO, timeout=300, check=False
    )
    assert out.returncode == 0, out.stderr[-3000:]
    assert "a remark nobody expected" in out.stderr
    for remark in ("LeafSpec", "The dirpath has changed", "on_before_batch_transfer"):
        assert remark not in out.stderr, out.stderr
