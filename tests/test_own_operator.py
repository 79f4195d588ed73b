"""The README's "Your own fusion operator": a class in the user's own module, a YAML in the user's config folder,
and a sweep that puts it beside a built-in operator, without touching ablate, run with the installed ``ablate``
command (``python -m ablate`` finds a module in the folder it runs in by Python's own rule; the console script
puts that folder on the path itself)."""

import os
import subprocess
import sys
import textwrap
from pathlib import Path

from mlflow.tracking import MlflowClient

from tests.scaleout import SERIAL, TINY
from tests.stores import seed_data, seed_store


def test_a_users_operator_sweeps_beside_a_built_in_one(tmp_path):
    (tmp_path / "my_ops.py").write_text(
        textwrap.dedent('''
        from torch import nn


        class Product(nn.Module):
            """Element-wise product of the modalities' features."""

            def __init__(self, channels: int, num_inputs: int = 2) -> None:
                super().__init__()

            def forward(self, features):
                out = features[0]
                for f in features[1:]:
                    out = out * f
                return out
    ''')
    )
    (tmp_path / "myconf" / "fusion").mkdir(parents=True)
    (tmp_path / "myconf" / "fusion" / "product.yaml").write_text("_target_: my_ops.Product\n_partial_: true\n")
    # the two jobs one after the other: the user's operator, not parallelism, is what this tests
    args = ["-m", "fusion=sum,product", f"hydra.searchpath=[file://{tmp_path / 'myconf'}]", SERIAL, *TINY]
    seed_store(tmp_path)
    seed_data(tmp_path)
    script = Path(sys.executable).parent / "ablate"  # the console script pip installed beside this interpreter
    env = {k: v for k, v in os.environ.items() if k not in ("MLFLOW_TRACKING_URI", "PYTHONPATH")}
    done = subprocess.run([str(script), *args], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=900)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    client = MlflowClient(f"sqlite:///{tmp_path / 'mlflow.db'}")
    exp = client.get_experiment_by_name("ablate")
    jobs = client.search_runs([exp.experiment_id], "tags.kind = 'job'")
    assert {r.data.tags["row"]: r.info.status for r in jobs} == {"fusion=sum": "FINISHED", "fusion=product": "FINISHED"}
    product = next(r for r in jobs if r.data.tags["row"] == "fusion=product")
    assert product.data.params["fusion._target_"] == "my_ops.Product"
    table = (tmp_path / "results" / "ablate.md").read_text().split("All metrics:")[0]
    rows = [line.split("|")[1].strip() for line in table.splitlines() if line.startswith("| fusion")]
    assert rows == ["fusion=sum", "fusion=product"]  # the order typed; the first is the reference
