"""Figures of `python -m ablate` runs on a GPU, read from what the runs left, into ``results/paper_scale_sweeps.json``
(``python -m ablate.check_paper`` lists them in ``results/paper_scale.md``, section "Through `python -m ablate` on a
GPU").

    python bench/gpu_sweeps.py table --dir multirun/<date>/<time> --log table.log --smi smi.csv
        --command "python -m ablate -m experiment=chinet_table2 trainer=gpu ..." [--gpu "NVIDIA H200"]
    python bench/gpu_sweeps.py row --train-log paper.log [--test-log paper2.log] --smi smi.csv --command "..."

``table``: a sweep's folder (its records ``runs/<table>.csv`` and its table ``<table>.md``) and its log: the jobs,
how many ran at once, each job's seconds (from its start, experts included, to its end), the jobs' wall time, the
command's (the log's first line to its last: the data, the plan, the jobs, the latency timing and the table), the
plan's estimate of a job (the sweep log's ``Sweep plan`` lines), each comparison's verdict beside the published
table's (``results/<table>.md``), the sweep's rows beside the published records (``<table>_vs_published.md``),
and the GPU's utilisation and memory in use while the jobs ran (``nvidia-smi
--query-gpu=timestamp,utilization.gpu,memory.used,power.draw --format=csv,noheader -l 1``).

``row``: one job's log (its progress lines, ``epoch e/E, step s/S``, and its ``FINISHED`` line): the seconds per
training step between progress lines (validation at each epoch's end included), the test's seconds (from the last
progress line to ``FINISHED``) and its metrics, and the GPU's utilisation and memory while it trained and while it
tested. A job stopped in its test and resumed from its checkpoint (the same command again) gives two logs: the
training figures come from ``--train-log``, the test's from ``--test-log``.

Log lines carry the time of day only: the runs are taken to be of the day ``--date`` (the nvidia-smi file's first
date by default). Every time is read as UTC, the GPU machines' clock.
"""

from __future__ import annotations

import argparse
import csv
import json
import re
import statistics
import sys
from datetime import datetime, timedelta, timezone
from pathlib import Path
from typing import Any

import pandas as pd

ROOT = Path(__file__).resolve().parent.parent
JSON = ROOT / "results" / "paper_scale_sweeps.json"
STAMP = re.compile(r"^\[(\d\d:\d\d:\d\d)\]")
PROGRESS = re.compile(r"^\[(\d\d:\d\d:\d\d)\]\[ablate\.jobs\.progress_lines\] epoch \d+/\d+, step (\d+)/(\d+)")
FINISHED = re.compile(r"^\[(\d\d:\d\d:\d\d)\]\[ablate\.jobs\.job\] FINISHED .*?: (.*)$")
PLAN = re.compile(r"Sweep plan: (\d+) job\(s\).*?, (\d+) at a time")
PLAN_JOB = re.compile(r"\[ablate\.sweep\.plan\]\s+\S+ seed \d+: ~([\d.]+) (min|s) \((measured|as the measured)\)")
VERDICT = re.compile(r"^(.+? vs .+?) \((?:reference|top vs second)\): (.+?)(?: at look \d+)? \(n = (\d+), Δ ([^ ]+) ")


def smi(path: Path) -> list[tuple[datetime, float, float]]:
    """(time, utilisation %, memory used in GiB) per line of an nvidia-smi CSV."""
    out = []
    with path.open() as f:
        for row in csv.reader(f):
            if len(row) >= 3 and "%" in row[1]:
                when = datetime.strptime(row[0].strip(), "%Y/%m/%d %H:%M:%S.%f")
                out.append((when, float(row[1].split()[0]), float(row[2].split()[0]) / 1024))
    return out


def gpu_between(samples: list[tuple[datetime, float, float]], start: datetime, end: datetime) -> dict[str, float]:
    """Mean and peak utilisation and peak memory in use between ``start`` and ``end``."""
    inside = [s for s in samples if start <= s[0] <= end]
    if not inside:
        return {}
    return {
        "util_mean": round(statistics.fmean(s[1] for s in inside), 1),
        "util_max": max(s[1] for s in inside),
        "mem_max_gib": round(max(s[2] for s in inside), 1),
        "samples": len(inside),
    }


def utc(ms: float) -> datetime:
    """A record's time (ms since the epoch) as a naive UTC time, as nvidia-smi and the logs print it."""
    return datetime.fromtimestamp(ms / 1000.0, tz=timezone.utc).replace(tzinfo=None)


def at(day: datetime, clock: str) -> datetime:
    return datetime.combine(day.date(), datetime.strptime(clock, "%H:%M:%S").time())


def verdicts(md: Path) -> dict[str, str]:
    """Each comparison's verdict line of a rendered table: ``{"A vs B": "verdict (n = .., Δ ..)"}``."""
    out = {}
    for line in md.read_text().splitlines():
        if m := VERDICT.match(line):
            out[m.group(1)] = f"{m.group(2)} (n = {m.group(3)}, Δ {m.group(4)})"
    return out


def beside(md: Path) -> list[dict[str, str]]:
    """The rows of a sweep's comparison with the published records (``<table>_vs_published.md``), by its columns."""
    if not md.exists():
        return []
    lines = [line for line in md.read_text().splitlines() if line.startswith("|")]
    if len(lines) < 3:
        return []
    names = [c.strip() for c in lines[0].strip("|").split("|")]
    return [dict(zip(names, (c.strip() for c in line.strip("|").split("|")))) for line in lines[2:]]


def table(args: argparse.Namespace, samples: list, day: datetime) -> dict[str, Any]:
    folder = Path(args.dir)
    # the table's records, not their .curves.csv beside them
    records = next((p for p in sorted((folder / "runs").glob("*.csv")) if "." not in p.stem), None)
    if records is None:
        raise SystemExit(f"{folder / 'runs'}: no records (<table>.csv) of a sweep there")
    name = records.stem
    runs = pd.read_csv(records)
    runs = runs[~runs["row"].astype(str).str.startswith("expert")] if "row" in runs else runs
    began = runs["job_started"] if "job_started" in runs else runs["started"]
    job_s = (runs["ended"] - began) / 1000.0
    start, end = (utc(ms) for ms in (began.min(), runs["ended"].max()))
    log = Path(args.log).read_text()
    stamps = [at(day, m.group(1)) for m in map(STAMP.match, log.splitlines()) if m]
    plan, estimates = (
        PLAN.search(log),
        [float(v) * (60 if unit == "min" else 1) for v, unit, how in PLAN_JOB.findall(log) if how == "measured"],
    )
    gpu = args.gpu or str(runs.get("made_gpu", pd.Series([""])).fillna("").iloc[0]) or "?"
    return {
        "kind": "table",
        "table": name,
        "command": args.command,
        "gpu": gpu,
        "cpu": str(runs["made_cpu"].iloc[0]),
        "precision": str(runs["made_precision"].iloc[0]),
        "date": day.date().isoformat(),
        "jobs": len(runs),
        "at_a_time": int(plan.group(2)) if plan else None,
        "job_s": [round(job_s.mean(), 1), round(job_s.min(), 1), round(job_s.max(), 1)],
        "wall_s": round((end - start).total_seconds(), 1),
        "command_s": round((stamps[-1] - stamps[0]).total_seconds(), 1) if stamps else None,
        "plan_job_s": round(statistics.fmean(estimates), 1) if estimates else None,
        "gpu_jobs": gpu_between(samples, start, end),
        "verdicts": verdicts(folder / f"{name}.md"),
        "published_verdicts": verdicts(ROOT / "results" / f"{name}.md"),
        "beside_published": beside(folder / f"{name}_vs_published.md"),
    }


def row(args: argparse.Namespace, samples: list, day: datetime) -> dict[str, Any]:
    train = Path(args.train_log).read_text().splitlines()
    test = Path(args.test_log or args.train_log).read_text().splitlines()
    points = [(at(day, m.group(1)), int(m.group(2)), int(m.group(3))) for m in map(PROGRESS.match, train) if m]
    if len(points) < 3:
        raise SystemExit(f"{args.train_log}: fewer than 3 progress lines, no step time")
    steady = points[1:]  # the first interval holds the warm-up (cuDNN's autotuning, the loader's start)
    rates = [(b[0] - a[0]).total_seconds() / (b[1] - a[1]) for a, b in zip(steady, steady[1:]) if b[1] > a[1]]
    done = [m for m in map(FINISHED.match, test) if m]
    last = [at(day, m.group(1)) for m in map(PROGRESS.match, test) if m]
    if not done or not last:
        raise SystemExit(f"{args.test_log or args.train_log}: no FINISHED line after a progress line")
    finished = at(day, done[-1].group(1))
    metrics = dict(kv.split("=", 1) for kv in done[-1].group(2).split(", "))
    return {
        "kind": "row",
        "command": args.command,
        "gpu": args.gpu or "?",
        "date": day.date().isoformat(),
        "steps": points[-1][1],
        "step_s": round(statistics.median(rates), 3),
        "steps_per_epoch": points[1][1] - points[0][1],
        "test_s": round((finished - last[-1]).total_seconds(), 1),
        "metrics": {k: float(v) for k, v in metrics.items()},
        "gpu_training": gpu_between(samples, points[0][0] - timedelta(seconds=5), points[-1][0]),
        "gpu_test": gpu_between(samples, last[-1], finished),
        "resumed_for_test": bool(args.test_log and args.test_log != args.train_log),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("kind", choices=["table", "row"])
    parser.add_argument("--dir", help="table: the sweep's folder (multirun/<date>/<time>)")
    parser.add_argument("--log", help="table: the sweep's log")
    parser.add_argument("--train-log", help="row: the job's log")
    parser.add_argument("--test-log", help="row: the log of the job's test, where it was resumed for it")
    parser.add_argument("--smi", required=True, action="append", help="nvidia-smi's CSV over the runs (repeatable)")
    parser.add_argument("--command", required=True, help="the command the figures are of")
    parser.add_argument("--gpu", help="the GPU's name (a table: read from its records where they name it)")
    parser.add_argument("--date", help="the day of the logs' times (default: the nvidia-smi file's first)")
    parser.add_argument("--json", default=str(JSON))
    args = parser.parse_args(argv)
    if args.kind == "table" and not (args.dir and args.log):
        parser.error("table needs --dir and --log")
    if args.kind == "row" and not args.train_log:
        parser.error("row needs --train-log")
    samples = sorted(s for path in args.smi for s in smi(Path(path)))
    if not samples:
        parser.error(f"{', '.join(args.smi)}: no nvidia-smi lines")
    day = datetime.fromisoformat(args.date) if args.date else samples[0][0]
    entry = (table if args.kind == "table" else row)(args, samples, day)
    path = Path(args.json)
    entries = json.loads(path.read_text()) if path.exists() else []
    entries = [e for e in entries if (e["kind"], e["command"]) != (entry["kind"], entry["command"])] + [entry]
    path.write_text(json.dumps(entries, indent=1, ensure_ascii=False) + "\n")
    print(json.dumps(entry, indent=1, ensure_ascii=False))
    return 0


if __name__ == "__main__":
    sys.exit(main())
