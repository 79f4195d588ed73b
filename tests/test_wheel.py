"""The wheel runs: built from the checkout, installed into a fresh virtual environment (which finds torch and the other
dependencies where this one has them), its `ablate` and `ablate-report` commands run a smoke table and the report
from an empty folder, with the configs inside the package; what they write lands in that folder, never in
site-packages."""

from __future__ import annotations

import os
import re
import site
import subprocess
import sys
import venv
from pathlib import Path

from tests.scaleout import REPO


def test_the_wheel_runs_a_smoke_table_and_the_report_from_an_empty_folder(tmp_path: Path) -> None:
    wheels = tmp_path / "wheels"
    build = [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q", "-w", str(wheels)]
    subprocess.run([*build, str(REPO)], check=True, capture_output=True, timeout=300)
    (wheel,) = wheels.glob("ablate_fusion-*.whl")
    env_dir = tmp_path / "env"
    venv.EnvBuilder(with_pip=False).create(env_dir)
    packages = next((env_dir / "lib").glob("python3*/site-packages"))
    (packages / "deps.pth").write_text(site.getsitepackages()[0] + "\n")  # torch and the rest, not ablate
    install = [sys.executable, "-m", "pip", "--python", str(env_dir / "bin" / "python"), "install", "-q", "--no-deps"]
    subprocess.run([*install, str(wheel)], check=True, capture_output=True, timeout=300)
    installed = sorted(p for p in (packages / "ablate").rglob("*") if "__pycache__" not in p.parts)
    assert (packages / "ablate" / "conf" / "config.yaml").is_file() and (packages / "ablate" / "py.typed").is_file()

    work = tmp_path / "work"
    work.mkdir()
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "MLFLOW_TRACKING_URI")}
    smoke = ["-m", "experiment=chinet_table2", "row=unet,fusenet", "scale=smoke", "data.synth.frames=20"]
    smoke += ["hydra/launcher=basic", "comp_time.repeats=2", "publish=true"]
    out = subprocess.run(
        [str(env_dir / "bin" / "ablate"), *smoke], cwd=work, env=env, capture_output=True, text=True, timeout=600
    )
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
    assert "site-packages/ablate/__init__.py" in subprocess.run(
        [str(env_dir / "bin" / "python"), "-c", "import ablate; print(ablate.__file__)"],
        cwd=work, env=env, capture_output=True, text=True,
    ).stdout  # fmt: skip
    report = subprocess.run(
        [str(env_dir / "bin" / "ablate-report"), "experiment=chinet_table2"],
        cwd=work, env=env, capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert report.returncode == 0, report.stderr[-3000:]
    # each command's --help points to documentation that was installed with it
    for command in ("ablate", "ablate-report"):
        said = subprocess.run(
            [str(env_dir / "bin" / command), "--help"], cwd=work, env=env, capture_output=True, text=True, timeout=120
        ).stdout
        pages = [Path(p) for p in re.findall(r"(/\S+/docs/[a-z]+\.md)", said)]
        assert pages and all(p.is_file() and packages in p.parents for p in pages), said[-1500:]
    for name in ("mlflow.db", "results/chinet_table2.md", "results/runs/chinet_table2.csv", "data"):
        assert (work / name).exists(), name
    assert sorted(p for p in (packages / "ablate").rglob("*") if "__pycache__" not in p.parts) == installed
