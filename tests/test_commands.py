"""One way to call each command: ``--help`` prints its usage and exits 0, a bad option is one ``error:`` line on stderr
and exit status 2 (:mod:`ablate.cli`), and neither trains, composes or imports torch. Run as a user runs them, in
a process of their own; the Hydra app calls itself ``ablate``."""

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from ablate import cli
from tests.scaleout import REPO

COMMANDS = ["ablate.report", "ablate.latency", "ablate.diagnose", "ablate.check_paper"]
BAD = [
    ("ablate.report", ["--bogus"]),
    ("ablate.report", ["experiment"]),  # no `=`
    ("ablate.report", ["--reproduce", "row=unet"]),  # no experiment=
    ("ablate.report", ["--parity", "experiment=chinet_table2", "row=unet", "row=chinet"]),
    ("ablate.report", ["--reproduce", "--parity", "experiment=chinet_table2", "row=unet"]),
    ("ablate.latency", []),  # no experiment=
    ("ablate.latency", ["experiment=chinet_table2", "--rounds", "5"]),
    ("ablate.diagnose", ["experts_only=maybe"]),
    ("ablate.diagnose", ["=smoe_table1"]),
    ("ablate.check_paper", ["budget_min=soon"]),
    ("ablate.check_paper", ["--force"]),
]


def run(cwd: Path, module: str, *args: str) -> subprocess.CompletedProcess[str]:
    """``python -m module args`` in ``cwd`` (where it must write nothing)."""
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    out = subprocess.run(
        [sys.executable, "-m", module, *args], capture_output=True, text=True, timeout=120, cwd=cwd, env=env
    )
    assert not any(cwd.iterdir()), sorted(cwd.rglob("*"))
    return out


@pytest.mark.parametrize("module", COMMANDS)
def test_help_prints_the_usage_naming_the_command_and_exits_0(module: str, tmp_path: Path) -> None:
    out = run(tmp_path, module, "--help")
    assert out.returncode == 0, out.stderr
    assert out.stdout.startswith(f"usage: python -m {module} "), out.stdout[:300]
    assert "key=value" in out.stdout and "exit status:" in out.stdout and out.stderr == ""


@pytest.mark.parametrize(("module", "args"), BAD, ids=[f"{m}-{' '.join(a) or 'none'}" for m, a in BAD])
def test_a_bad_option_is_one_error_line_and_status_2(module: str, args: list[str], tmp_path: Path) -> None:
    out = run(tmp_path, module, *args)
    assert out.returncode == 2, out.stdout[-1000:] + out.stderr[-2000:]
    lines = out.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and f"python -m {module} --help" in lines[0], lines
    assert out.stdout == ""


@pytest.mark.parametrize("module", COMMANDS)
@pytest.mark.parametrize("args", [["--help"], ["--bogus"]])
def test_help_and_a_bad_option_import_no_torch(module: str, args: list[str], tmp_path: Path) -> None:
    # nor MLflow nor the tables: `python -m ablate.report --help` took 5-7 s while it imported them at its top
    code = (
        "import runpy, sys\n"
        f"sys.argv = ['{module}', *{args!r}]\n"
        "try:\n"
        f"    runpy.run_module('{module}', run_name='__main__', alter_sys=True)\n"
        "except SystemExit as exit:\n"
        "    status = exit.code\n"
        "heavy = {'torch', 'lightning', 'mlflow', 'ablate.tables'} & set(sys.modules)\n"
        "sys.exit(10 if heavy else status)\n"
    )
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=tmp_path, env=env
    )
    assert out.returncode == (0 if args == ["--help"] else 2), out.stderr[-2000:]


def test_the_latency_help_names_the_configs_options(tmp_path: Path) -> None:
    out = run(tmp_path, "ablate.latency", "--help").stdout
    for option in ("comp_time.repeats", "comp_time.warmup", "comp_time.threads", "comp_time.device"):
        assert option in out
    assert "comp_time.after_sweep=false" in out and "latency.rounds" not in out and "latency.enabled" not in out


def test_the_hydra_app_calls_itself_ablate(tmp_path: Path) -> None:
    out = run(tmp_path, "ablate", "--help")
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.startswith("ablate: ") and "__main__" not in out.stdout
    assert "python -m ablate.report" in out.stdout


def test_options_and_overrides_come_in_any_order() -> None:
    args = cli.report(None, ["experiment=chinet_table2", "--reproduce", "row=unet", "seed=2"])
    assert args.reproduce and not args.parity
    assert args.overrides == ["experiment=chinet_table2", "row=unet", "seed=2"]
    assert not cli.report(None, ["logger.tracking_uri=sqlite:////tmp/a.db", "+x.y=1", "~z"]).reproduce


def test_a_commands_own_keys_are_read_and_taken_out_of_the_overrides() -> None:
    args = cli.diagnose(None, ["experts_only=YES", "scale=smoke"])
    assert args.experts_only is True and args.overrides == ["scale=smoke", "experiment=smoe_table1"]
    assert cli.diagnose(None, ["experiment=smoe_table2"]).overrides == ["experiment=smoe_table2"]
    assert cli.diagnose(None, ["row=smoe_rgb,smoe_fpn"]).row == ["smoe_rgb", "smoe_fpn"] and args.row == []
    args = cli.check_paper(None, ["experiment=a,b", "budget_min=-1", "reuse=true", "trainer.threads=2"])
    assert args.experiment == ["a", "b"] and args.row == [] and args.budget_min == -1.0
    assert args.reuse and not args.force and args.overrides == ["trainer.threads=2"]


def test_main_called_from_python_ends_a_bad_option_like_the_command(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as ended:
        cli.check_paper(None, ["experiment=nope"], tables=["chinet_table2", "smoe_table1"])
    assert ended.value.code == cli.USAGE
    err = capsys.readouterr().err.splitlines()
    assert err == [
        "error: no experiment nope; have chinet_table2, smoe_table1 (see python -m ablate.check_paper --help)"
    ]
    from ablate.report import main

    with pytest.raises(SystemExit) as ended:
        main(["--parity", "row=unet"])
    assert ended.value.code == 2 and capsys.readouterr().err.startswith("error: --parity needs experiment=")


def test_a_report_against_a_server_that_does_not_answer_fails_within_its_budget_naming_it(tmp_path: Path) -> None:
    # nothing listens on the port: the store (not the report) waits logger.outage_s, then one line names the server
    from tests.scaleout import free_port

    uri = f"http://127.0.0.1:{free_port()}"
    env = {k: v for k, v in os.environ.items() if k != "MLFLOW_TRACKING_URI"}
    started = time.monotonic()
    out = subprocess.run(
        [sys.executable, "-m", "ablate.report", "--publish", "experiment=chinet_table2", f"logger.tracking_uri={uri}",
         "logger.outage_s=3"],
        capture_output=True, text=True, timeout=120, cwd=tmp_path, env={**env, "PYTHONPATH": str(REPO)},
    )  # fmt: skip
    waited = time.monotonic() - started
    assert out.returncode == 1, out.stderr
    errors = [line for line in out.stderr.splitlines() if line.startswith("error:")]  # beside the waiting notice
    assert len(errors) == 1 and uri.split("//")[1] in errors[0] and "Traceback" not in out.stderr, out.stderr
    assert waited < 60, f"waited {waited:.0f} s for a server that does not answer, with logger.outage_s=3"


def test_the_seeds_come_from_the_race_alone_and_scale_seeds_is_refused(tmp_path: Path) -> None:
    # a table's seeds are its race plan (table.seeds, from scale.race): an option nothing reads is refused, naming it
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    args = [sys.executable, "-m", "ablate", "-m", "experiment=chinet_table2", "scale=smoke", "scale.seeds=2"]
    out = subprocess.run(args, capture_output=True, text=True, timeout=120, cwd=tmp_path, env=env)
    assert out.returncode != 0 and "scale.seeds" in out.stderr and "Traceback" not in out.stderr, out.stderr
    assert not (tmp_path / "mlflow.db").exists()  # refused before any job or store
