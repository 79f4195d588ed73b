"""bench/ci_profile.py reads py-spy's raw profiles as they are: a command line over several lines (``python -c``
with a script, whose lines may end in a number or hold quotes) stays one record of its process, a blocked thread is
not counted busy, and each busy sample lands in its activity and its process's kind."""

from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))

import ci_profile  # noqa: E402

WARM = f'{ci_profile.WARM}, socket, sys\nrequest = json.loads(line)\n    code = 0\nexcept SystemExit:\n    code = 1\nprint("done")'
PYTEST = 'process 1:"python -m pytest -q"'
WORKER = f'{PYTEST};process 2:"python -u -c import sys;exec(eval(sys.stdin.readline()))"'
RAW = "\n".join(
    [
        # a command forked from the warm interpreter: its command line holds quotes and lines ending in a number
        f'{WORKER};process 3:"python -c {WARM}";<module> (<string>:105);run_module (<frozen runpy>:226);'
        "fit (ablate/jobs/train.py:10);_run_stage (lightning/pytorch/trainer/trainer.py:1);conv2d (torch/nn/functional.py:5) 50",
        # the same command importing torch
        f'{WORKER};process 3:"python -c {WARM}";<module> (<string>:105);run_module (<frozen runpy>:226);'
        "_find_and_load (<frozen importlib._bootstrap>:1176);<module> (torch/__init__.py:1) 25",
        # the warm interpreter itself composing nothing, but blocked on its socket: not busy
        f'{WORKER};process 3:"python -c {WARM}";<module> (<string>:80);select (selectors.py:468) 1000',
        # a joblib worker composing a config
        f'{WORKER};process 4:"python -m joblib.externals.loky.backend.popen_loky_posix";'
        "main (ablate/__main__.py:41);compose (hydra/compose.py:30);_merge (omegaconf/basecontainer.py:9) 25",
        # a test's own code, in the pytest worker
        f"{WORKER};<module> (<string>:1);test_x (tests/test_x.py:3);frame (pandas/core/frame.py:1) 10",
        # a process with no Python frame
        'process 9:"raylet" 500',
    ]
)


def test_a_raw_profile_is_summarised_per_activity_and_per_process_kind(tmp_path):
    raw = tmp_path / "spy.txt"
    raw.write_text(RAW + "\n")
    text = ci_profile.summarise(raw, rate=25, wall=None)
    assert text.startswith("busy CPU 4 s")  # 110 busy samples at 25 a second; the blocked and frameless left out
    assert "| training and testing | 2 | 45.5 % |" in text
    assert "| import | 1 | 22.7 % |" in text
    assert "| config composition | 1 | 22.7 % |" in text
    assert "| other | 0 | 9.1 % |" in text
    assert "| command forked from the warm interpreter | 3 | 1 |" in text
    assert "| joblib worker | 1 | 0 |" in text
    assert "| pytest worker | 0 | 0 |" in text
    assert "warm interpreter (its imports)" not in text and "other process" not in text
