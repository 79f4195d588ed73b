"""What a table's runs carry beside them (ablate.tables.kept): shared by every frame derived from the runs, not
deep-copied into each (pandas copies ``attrs`` into every column read and selection)."""

import pickle

import numpy as np
import pandas as pd

from ablate.tables.kept import keep, kept


def test_the_counts_kept_beside_the_runs_are_shared_by_every_frame_derived_from_them() -> None:
    runs = pd.DataFrame({"row": ["a", "a", "b"], "seed": [0, 1, 0], "x": [1.0, 2.0, 3.0]})
    frames = pd.DataFrame(np.zeros((1000, 50)))
    keep(runs, "frames", frames)
    for derived in (runs["x"], runs[runs["row"] == "a"], runs.loc[:, ["seed", "x"]], runs.copy(deep=True)):
        assert kept(derived, "frames") is frames
    assert kept(pickle.loads(pickle.dumps(runs)), "frames").equals(frames)
    runs.attrs["trials"] = trials = pd.DataFrame({"seconds": [60.0]})  # put there as it is: read as it is
    assert kept(runs, "trials") is trials and kept(runs, "detections") is None
