"""The section of ``results/paper_scale.md`` on runs through ``python -m ablate`` on a GPU: the figures
``bench/gpu_sweeps.py`` read from their records, logs and nvidia-smi's samples, kept in
``results/paper_scale_sweeps.json``."""

from __future__ import annotations

from typing import Any


def _gpu(figures: dict[str, Any]) -> str:
    if not figures:
        return "no nvidia-smi samples"
    return (
        f"utilisation {figures['util_mean']:.0f} % on average (peak {figures['util_max']:.0f} %), memory in use up "
        f"to {figures['mem_max_gib']:.1f} GiB (CUDA contexts included; nvidia-smi, {figures['samples']} samples "
        "a second apart)"
    )


def _column(row: dict[str, str], head: str) -> str:
    """The name of ``row``'s column that starts with ``head``."""
    return next(name for name in row if name.startswith(head))


def _table(e: dict[str, Any]) -> list[str]:
    mean, low, high = e["job_s"]
    plan = f"; the sweep's plan had estimated {e['plan_job_s']:.0f} s a job" if e.get("plan_job_s") else ""
    out = [
        f"### {e['table']} on an {e['gpu']} ({e['date']})",
        "",
        f"`{e['command']}`",
        "",
        f"- {e['jobs']} jobs, {e['at_a_time']} at a time, {e['precision']}, on the GPU beside an {e['cpu']}: a job "
        f"took {mean:.0f} s on average ({low:.0f}-{high:.0f} s), start to end{plan}. The jobs' wall time "
        f"{e['wall_s']:.0f} s; the whole command {e['command_s']:.0f} s (data, plan, jobs, latency timing, table).",
        f"- The GPU while the jobs ran: {_gpu(e['gpu_jobs'])}.",
        *(
            f"- {r['Row']}: {r['Yours (mean, n)']} here against {r['Published (mean, n)']} published; "
            f"{r['Your seeds inside']} seeds inside the published 95 % prediction interval {r[pi]}; differs: "
            f"{r[differ] or 'nothing'}."
            for r in e.get("beside_published") or []
            for pi, differ in [(_column(r, "Published 95 %"), _column(r, "Numerics"))]
        ),
        "",
        f"| comparison | here | published (results/{e['table']}.md) | same verdict |",
        "|---|---|---|---|",
    ]
    published = e.get("published_verdicts") or {}
    for name, verdict in e["verdicts"].items():
        theirs = published.get(name, "—")
        same = "yes" if theirs.split(" (")[0] == verdict.split(" (")[0] else "no"
        out.append(f"| {name} | {verdict} | {theirs} | {same} |")
    return out + [""]


def _row(e: dict[str, Any]) -> list[str]:
    metrics = ", ".join(f"{k} {v:g}" for k, v in e["metrics"].items())
    resumed = (
        " The first run was stopped during its test; the same command again resumed it from its last checkpoint, "
        "retrained the steps since, and tested: the test's figures are the second run's."
        if e.get("resumed_for_test")
        else ""
    )
    return [
        f"### One row at `scale=paper` on an {e['gpu']} ({e['date']})",
        "",
        f"`{e['command']}`",
        "",
        f"- {e['steps']} training steps, {e['steps_per_epoch']} an epoch: {e['step_s']:.3f} s a step (the median "
        "between progress lines, each epoch's validation included).",
        f"- The GPU while it trained: {_gpu(e['gpu_training'])}.",
        f"- Its test took {e['test_s']:.0f} s; the GPU meanwhile: {_gpu(e['gpu_test'])}. Test metrics: {metrics}."
        + resumed,
        "",
    ]


def sweeps_section(entries: list[dict[str, Any]]) -> list[str]:
    """``results/paper_scale_sweeps.json`` as the markdown's last section; nothing where it has no entries."""
    if not entries:
        return []
    out = [
        "## Through `python -m ablate` on a GPU",
        "",
        "Whole commands as a user types them, with `trainer=gpu` (bf16 autocast, fp32 weights). Figures read by "
        "`bench/gpu_sweeps.py` from the runs' records, logs and nvidia-smi's samples; kept in "
        "results/paper_scale_sweeps.json. A table's verdicts here stopped where its wall-time budget stopped its "
        "race; the published table's are those of its own race, on the CPU.",
        "",
    ]
    for e in entries:
        out += _table(e) if e["kind"] == "table" else _row(e)
    return out
