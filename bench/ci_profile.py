"""Where the test suite's CPU goes: every Python process of ``make test`` sampled by py-spy (the pytest workers,
the commands they fork from their warm interpreter, the sweeps' joblib, Ray and submitit workers, the processes
spawned by multiprocessing (the tracking server's workers, the data generator's pools, DDP), the servers), each busy
sample put in one activity:

- **import**: a module being imported (a fresh process imports torch, Lightning and MLflow: seconds);
- **training and testing**: inside Lightning's fit or test loop;
- **config composition**: Hydra and OmegaConf (composing, resolving, parsing overrides);
- **store**: MLflow, SQLAlchemy and Alembic (the store's queries and its schema);
- **figures**: matplotlib;
- **other torch**, **other** (the project's own code, numpy, pandas, the tests).

A sample counts where its innermost frame is Python and not a blocking call (a wait, a read, a sleep): py-spy also
samples threads blocked in C, which would count a waiting process as busy. The seconds are samples over the rate:
py-spy slows what it samples by a few percent, so they add up to somewhat more than the run's CPU time.

Usage (py-spy is not a dependency: ``pip install py-spy``; it needs ptrace, as in a container run as root):

    python bench/ci_profile.py --record          # runs the README's test command under py-spy, then the summary
    python bench/ci_profile.py --raw spy.txt     # the summary of a raw profile recorded earlier

The figures depend on the CPU (printed first) and on what else runs: measure on an idle machine.
"""

from __future__ import annotations

import argparse
import collections
import re
import shlex
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

#: Samples a second (py-spy's ``--rate``): 25 keeps its overhead small over a 10-minute run.
RATE = 25
#: The README's test command (``make test``), without the set-up.
TESTS = "-m pytest -q -n auto --dist loadfile --no-loadscope-reorder -p no:cacheprovider"
#: Innermost functions that wait rather than compute.
BLOCKING = re.compile(r"wait|select|sleep|recv|read|accept|poll|acquire|communicate|join|_worker|serve_forever", re.I)
#: A Python frame of py-spy's raw format: ``function (file:line)``.
FRAME = re.compile(r"^(?P<function>.*) \((?P<file>[^()]*):\d+\)$")
#: A record of py-spy's raw format: the ``;``-separated stack, a space and its count. A process's command line may
#: span lines (``python -c`` with a script), so a record ends only where a frame (``...:line)``) or a process
#: (``process N:"..."``) is followed by the count.
RECORD = re.compile(r"(.*?[)\"]) (\d+)\n", re.S)
#: The first line of ``tests/forkserver.py``'s warm interpreter, which its forked commands' command line repeats.
WARM = "import importlib, json, os, selectors"
ACTIVITIES = ["import", "training and testing", "config composition", "store", "figures", "other torch", "other"]
LIBRARY = {
    "hydra": "config composition",
    "omegaconf": "config composition",
    "antlr4": "config composition",
    "yaml": "config composition",
    "mlflow": "store",
    "sqlalchemy": "store",
    "alembic": "store",
    "matplotlib": "figures",
    "torch": "other torch",
}


def activity(frames: list[str]) -> str:
    """The activity of one stack, outermost frame first (:data:`ACTIVITIES`)."""
    text = ";".join(frames)
    if "_find_and_load" in text:
        return "import"
    if re.search(r"_run_stage \(lightning/|fit_loop|evaluation_loop", text):
        return "training and testing"
    for frame in reversed(frames):
        match = FRAME.match(frame)
        if match and "/" in match["file"] and not match["file"].startswith("<"):
            return LIBRARY.get(match["file"].split("/")[0], "other")
    return "other"


def process_kind(stack: str) -> str:
    """What sort of process a stack was sampled in, from its command line (the last ``process N:"..."`` label of
    the stack; a command line may hold quotes, so it ends where the frames begin) and, for a command forked from
    the tests' warm interpreter (``tests/forkserver.py``, whose children keep its command line), its frames."""
    labels = list(re.finditer(r'(?:^|;)process \d+:"', stack))
    command, _, frames = stack[labels[-1].end() :].partition('";') if labels else ("", "", stack)
    kinds = [
        ("loky", "joblib worker"),
        ("ray", "Ray process"),
        ("submitit", "submitit job"),
        ("multiprocessing.spawn", "spawned by multiprocessing"),
        ("uvicorn", "tracking server"),
        ("mlflow ui", "tracking server"),
        ("exec(eval(sys.stdin", "pytest worker"),
        ("pytest", "pytest"),
    ]
    if WARM in command:
        forked = "run_module (<frozen runpy>" in frames or "run_path (<frozen runpy>" in frames
        return "command forked from the warm interpreter" if forked else "warm interpreter (its imports)"
    for marker, kind in kinds:
        if marker in command:
            return kind
    return "python -m ablate (fresh)" if "ablate" in command else "other process"


def summarise(raw: Path, rate: int, wall: float | None) -> str:
    """The summary table of a raw py-spy profile: busy CPU seconds per activity and per process kind."""
    by_activity: collections.Counter[str] = collections.Counter()
    by_kind: collections.defaultdict[str, collections.Counter[str]] = collections.defaultdict(collections.Counter)
    for match in RECORD.finditer(raw.read_text(errors="replace")):
        stack, count = match.group(1), int(match.group(2))
        frames = [f for f in stack.split(";") if FRAME.match(f)]
        if not frames or BLOCKING.search(FRAME.match(frames[-1])["function"]):  # type: ignore[index]
            continue
        act = activity(frames)
        by_activity[act] += count
        by_kind[process_kind(stack)][act] += count
    total = sum(by_activity.values())
    if not total:
        raise SystemExit(f"error: {raw} holds no busy Python samples (was it recorded with py-spy --format raw?)")
    lines = [f"busy CPU {total / rate:.0f} s" + (f" over {wall:.0f} s of wall time" if wall else ""), ""]
    lines += ["| activity | CPU s | share |", "|:--|--:|--:|"]
    lines += [f"| {a} | {by_activity[a] / rate:.0f} | {100 * by_activity[a] / total:.1f} % |" for a in ACTIVITIES]
    lines += ["", "| process | CPU s | of which import |", "|:--|--:|--:|"]
    for kind, acts in sorted(by_kind.items(), key=lambda kv: -sum(kv[1].values())):
        lines.append(f"| {kind} | {sum(acts.values()) / rate:.0f} | {acts['import'] / rate:.0f} |")
    return "\n".join(lines)


def record(out: Path, rate: int) -> float:
    """Run the test command under py-spy into ``out`` (raw format); its wall time."""
    spy = Path(sys.executable).with_name("py-spy")
    if not spy.exists():
        raise SystemExit(f"error: py-spy is not installed beside {sys.executable} (pip install py-spy)")
    command = [str(spy), "record", "--subprocesses", "--rate", str(rate), "--format", "raw", "-o", str(out), "--"]
    command += [sys.executable, *shlex.split(TESTS)]
    print("$ " + shlex.join(command), flush=True)
    began = time.monotonic()
    done = subprocess.run(command, cwd=ROOT)
    if done.returncode != 0:
        print(f"the tests ended with status {done.returncode}: the profile still counts what ran", file=sys.stderr)
    return time.monotonic() - began


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    group = parser.add_mutually_exclusive_group(required=True)
    group.add_argument("--record", action="store_true", help="profile the README's test command, then summarise")
    group.add_argument("--raw", type=Path, help="summarise a raw py-spy profile (py-spy record --format raw)")
    parser.add_argument("--out", type=Path, default=Path("ci_profile.txt"), help="where --record writes the profile")
    parser.add_argument("--rate", type=int, default=RATE, help="py-spy's samples a second (as recorded)")
    args = parser.parse_args()
    from ablate import hardware

    print(f"CPU: {hardware.cpu().model}, {hardware.cores()} cores")
    wall = record(args.out, args.rate) if args.record else None
    raw = args.out if args.record else args.raw
    if not raw.exists():
        raise SystemExit(f"error: no profile at {raw}")
    print(summarise(raw, args.rate, wall))
    return 0


if __name__ == "__main__":
    sys.exit(main())
