"""docs/tutorial.md, run as a user runs it: every ``bash`` block of the page in order, in an empty folder, with the
installed commands (``ablate`` and its siblings beside this interpreter) and nothing of the repository on the path.
The user's operator, row and table live in the user's folder only: the sweep's plan, its latency timing and its
table must all find them there."""

import os
import re
import subprocess
import sys
from pathlib import Path

from mlflow.tracking import MlflowClient

PAGE = Path(__file__).resolve().parents[1] / "docs" / "tutorial.md"


def blocks(text: str) -> list[str]:
    """The page's ``bash`` blocks, in order."""
    return re.findall(r"```bash\n(.*?)```", text, flags=re.DOTALL)


def test_the_tutorials_commands_run_as_written_and_make_the_users_table(tmp_path):
    commands = blocks(PAGE.read_text())
    assert len(commands) >= 5 and any(c.startswith("ablate -m experiment=my_table") for c in commands)
    env = {k: v for k, v in os.environ.items() if k not in ("MLFLOW_TRACKING_URI", "PYTHONPATH")}
    env["PATH"] = f"{Path(sys.executable).parent}{os.pathsep}{env.get('PATH', '')}"  # the installed commands
    said = []
    for command in commands:
        done = subprocess.run(
            ["bash", "-e", "-c", command], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=900
        )
        assert done.returncode == 0, f"{command}\n{done.stdout[-3000:]}\n{done.stderr[-3000:]}"
        said.append(done.stdout + done.stderr)
    sweep = next(s for c, s in zip(commands, said) if c.startswith("ablate -m"))
    assert "Sweep plan: 2 job(s)" in sweep and "Could not" not in sweep, sweep[-3000:]
    assert "Latency: smoe_product from" in sweep  # the user's row, composed from the user's folder
    assert "Product against sum fusion at the FPN" in said[-1]  # `head` of the table
    client = MlflowClient(f"sqlite:///{tmp_path / 'mlflow.db'}")
    exp = client.get_experiment_by_name("my_table")
    jobs = client.search_runs([exp.experiment_id], "tags.kind = 'job'")
    assert {r.data.tags["row"]: r.info.status for r in jobs} == {"smoe_sum": "FINISHED", "smoe_product": "FINISHED"}
    product = next(r for r in jobs if r.data.tags["row"] == "smoe_product")
    assert product.data.params["fusion._target_"] == "my_ops.Product"
    table = (tmp_path / "results" / "my_table.md").read_text()
    main = table.split("All metrics:")[0]
    assert [line.split("|")[1].strip() for line in main.splitlines() if line.startswith("| ")][1:] == [
        "Sum fusion",
        "Product fusion",
    ]
    # what the page says the footer says
    assert "Product fusion vs Sum fusion (reference): no verdict (n = 1" in table
    assert "±δ = 0.5 AP: half a point of AP" in table and "not measured" not in table
