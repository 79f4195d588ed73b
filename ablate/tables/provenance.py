"""Is a table's code still the code of its runs? Checks for the tables' footers.

A run records the commit it was made at (``git_commit`` tag, ``-dirty`` when the tree had changes) and its
resolved config, whose ``_target_`` entries name the classes and functions it built. The code a run depends on
is taken as those modules and every ``ablate`` module they import, transitively (read from the source with
:mod:`ast`; an import inside a function counts too). A package's ``__init__`` met only on the way to one of its
modules counts itself and the modules it imports *as modules* (``from ablate.fusion import ops_bifnet``, an import
for its registrations), not the names it re-exports (``from ablate.nn.vgg import VGG16SSD`` in ``ablate.nn``, there
for other importers): those count where a module names the package itself (``from ablate.nn import VGG16SSD``). So
a ChiNet run, which imports ``ablate.nn.unet``, does not depend on the VGG-16 it never builds. A file of that set
changed between the run's commit and the working tree makes the run a candidate: its numbers may not be what the code
gives today. Whether they are is judged by behaviour, not by file: a run that recorded a fingerprint
(:mod:`ablate.jobs.fingerprint`) has it recomputed on today's code and is flagged only where a component differs, so a
rename or a move flags nothing; a run without one (made before fingerprints) falls back to the file check. Config files are covered by the config hash: a row whose config changed gets a new hash and is trained
again. A metric whose rule changed is named outright (:func:`evaluators`): a run records the evaluator it was
scored with as its ``evaluator`` tag, and :data:`ablate.metrics.EVALUATORS` names today's.
"""

from __future__ import annotations

import ast
import functools
import subprocess
import tempfile
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import cast

import pandas as pd
from omegaconf import DictConfig, OmegaConf

from ablate.metrics import EVALUATORS
from ablate.store import Tracker
from ablate.store.fingerprint import cpu_chip, decode, differs, kernel_family

ROOT = Path(__file__).resolve().parents[2]


def module_file(name: str, root: Path = ROOT) -> Path | None:
    """The source file of module ``name`` (``a.b`` -> ``a/b.py`` or ``a/b/__init__.py``) under ``root``."""
    base = root.joinpath(*name.split("."))
    for path in (base.with_suffix(".py"), base / "__init__.py"):
        if path.is_file():
            return path
    return None


def _imported(path: Path, package: str, root: Path, modules_only: bool = False) -> set[str]:
    """The ``package`` names ``path`` imports; ``modules_only``: just those that are modules (``import a.b``,
    ``from a import b`` with ``a/b.py``), not the names imported from them."""
    stat = path.stat()
    plain, froms = _imports(path, stat.st_mtime_ns, stat.st_size)
    names = set(plain)
    for module, members in froms:  # `from module import member`: a module or a name
        names |= {m for m in members if module_file(m, root)} if modules_only else {*members, module}
    return {n for n in names if n == package or n.startswith(package + ".")}


@functools.lru_cache(maxsize=1024)
def _imports(path: Path, mtime_ns: int, size: int) -> tuple[tuple[str, ...], tuple[tuple[str, tuple[str, ...]], ...]]:
    """The absolute imports of the source ``path`` as of its ``mtime_ns`` and ``size``: the modules of ``import
    a.b``, and (module, its dotted members) of each ``from module import member``. Parsed once a process per version
    of the file: a report's tables ask for the same files again and again."""
    plain: list[str] = []
    froms: list[tuple[str, tuple[str, ...]]] = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            plain += [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            froms.append((node.module, tuple(f"{node.module}.{a.name}" for a in node.names)))
    return tuple(plain), tuple(froms)


def dependencies(targets: set[str], package: str = "ablate", root: Path = ROOT) -> set[Path]:
    """The source files of ``package`` that the dotted ``targets`` (``ablate.tasks.instance.InstanceTask``)
    import, transitively, with the files of the packages on the way (their ``__init__``, with the modules it
    imports as modules; see the module docstring)."""
    todo, seen, files = list(targets), set(), set()
    followed: dict[Path, str] = {}
    while todo:
        name = todo.pop()
        if name in seen or not (name == package or name.startswith(package + ".")):
            continue
        seen.add(name)
        parts = name.split(".")
        paths = [module_file(".".join(parts[:i]), root) for i in range(1, len(parts) + 1)]
        named = max((i for i, p in enumerate(paths) if p is not None), default=-1)  # the module the name is in
        for i, path in enumerate(paths):
            if path is None:
                continue
            files.add(path)
            how = "all" if i == named else "modules"  # the named module, or a package on the way to it
            if followed.get(path) not in (how, "all"):
                followed[path] = how
                todo.extend(_imported(path, package, root, modules_only=how == "modules"))
    return files


def changed_since(commit: str, paths: Sequence[str] = ("ablate", "conf"), root: Path = ROOT) -> set[Path] | None:
    """Files under ``paths`` that differ between ``commit`` and the working tree; None when git cannot tell (no
    checkout, an unknown commit)."""
    sha = commit.removesuffix("-dirty")
    try:
        out = subprocess.run(
            ["git", "diff", "--name-only", sha, "--", *paths], cwd=root, capture_output=True, text=True, check=True
        ).stdout
    except (OSError, subprocess.CalledProcessError):
        return None
    return {(root / line).resolve() for line in out.splitlines() if line}


def stale(commits: set[str], targets: set[str], root: Path = ROOT, package: str = "ablate") -> dict[str, list[str]]:
    """{commit: files the runs depend on that changed since it}, for the commits with such files; a commit git
    does not know maps to ``["unknown commit"]``."""
    deps = {p.resolve() for p in dependencies(targets, package, root)}
    out = {}
    for commit in sorted(commits):
        changed = changed_since(commit, [package], root)
        if changed is None:
            out[commit] = ["unknown commit"]
        elif hit := sorted(str(p.relative_to(root)) for p in changed & deps):
            out[commit] = hit
    return out


def evaluators(targets: set[str], root: Path = ROOT, package: str = "ablate") -> dict[str, str]:
    """{metric module: today's evaluator} (:data:`ablate.metrics.EVALUATORS`) for the metric modules that the
    dotted ``targets`` import, transitively (:func:`dependencies`)."""
    deps = {p.resolve() for p in dependencies(targets, package, root)}
    return {m: e for m, e in sorted(EVALUATORS.items()) if (f := module_file(m, root)) and f.resolve() in deps}


#: Recomputes a run's fingerprint from its resolved config (:func:`ablate.jobs.fingerprint.compute`): passed in by
#: the caller, the tables never import the job.
Recompute = Callable[[DictConfig], dict[str, list[float]]]


def config_of(tracker: Tracker, run_id: str) -> DictConfig:
    """The resolved config a run logged (its ``config.yaml`` artifact; a reused run's is its source's)."""
    run = tracker.get_run(run_id)
    source = run.data.tags.get("reused_from", run_id)
    with tempfile.TemporaryDirectory() as tmp:
        path = tracker.download_artifact(source, "config.yaml", tmp)
        return cast(DictConfig, OmegaConf.load(path))


def fingerprint_check(
    runs: pd.DataFrame, recompute: Recompute, config: Callable[[str], DictConfig]
) -> dict[str, str | None]:
    """{row: how its fingerprint differs today, in words (None: it does not)} for the rows of ``runs`` that carry
    a fingerprint, recomputed for each row's lowest seed: "its fingerprint's <component> differs from today's
    code", or, for a component its record predates, that the record lacks what today's code fingerprints."""
    out: dict[str, str | None] = {}
    with_tag = runs[runs["fingerprint"].fillna("") != ""] if "fingerprint" in runs else runs.iloc[0:0]
    for row, sel in with_tag.groupby("row", sort=True):
        first = sel.sort_values("seed").iloc[0]
        recorded = decode(first["fingerprint"])
        component = differs(recorded, recompute(config(first["run_id"])), across_kernels(first))
        out[str(row)] = (
            None
            if component is None
            else f"its fingerprint's {component} differs from today's code"
            if component in recorded
            else f"its fingerprint predates the {component} component that today's code computes for it"
        )
    return out


def across_kernels(run: pd.Series) -> bool:
    """Whether a recorded run's fingerprint came from other kernels than today's (:func:`ablate.store.fingerprint.
    kernel_family`: another instruction set's, or the same one's on another CPU): then only the components that
    rounding does not move are compared. A record that does not name its CPU's family and model is compared by its
    instruction set alone."""
    made = str(run.get("made_cpu") or "")
    recorded = kernel_family(str(run.get("cpu_kernels") or ""), str(run.get("cpu_isa") or ""), made)
    if not recorded:
        return False
    from ablate.hardware import cpu, kernels  # imports torch: only where a fingerprint is recomputed

    return recorded != kernel_family(kernels(), cpu=cpu().model if cpu_chip(made) else "")


def provenance(
    runs: pd.DataFrame, recompute: Recompute | None = None, config: Callable[[str], DictConfig] | None = None
) -> list[str]:
    """The footer's provenance: the commits of the table's runs (their ``git_commit`` tag: the ``ablate`` code that
    ran), and whether today's code still gives their numbers.

    Where files the runs build changed since a commit (:func:`stale`), the rows of that commit with a recorded
    fingerprint are recomputed with ``recompute`` (on the config ``config(run_id)`` returns) and flagged only where
    a component differs, named; runs without a fingerprint (made before it was recorded), or a caller that passes no
    ``recompute``, fall back to naming the changed files. One line when the runs come from one commit and nothing
    is flagged."""
    if not len(runs) or "git_commit" not in runs:
        return []
    commit = runs["git_commit"].fillna("unknown")
    counts = commit.value_counts().sort_index()
    named = ", ".join(f"{c[:12]}{'-dirty' if c.endswith('-dirty') else ''} ({n} runs)" for c, n in counts.items())
    head = f"Runs made at commit {named}"
    mixed = [] if len(counts) == 1 else [f"**Mixed commits**: the rows come from {len(counts)} commits."]
    lines: list[str] = []  # what is flagged
    targets = set(" ".join(runs["targets"].fillna("")).split()) if "targets" in runs else set()
    shas = {c.removesuffix("-dirty") for c in counts.index} - {"unknown"}
    changed = stale(shas, targets) if targets else {}
    checked = 0
    for sha, files in changed.items():
        sel = runs[commit.str.removesuffix("-dirty") == sha]
        has = sel["fingerprint"].fillna("") != "" if "fingerprint" in sel else pd.Series(False, index=sel.index)
        if recompute is not None and config is not None and has.any():
            for row, reason in fingerprint_check(sel[has], recompute, config).items():
                checked += 1
                if reason is not None:
                    lines.append(
                        f"**Numbers may have moved** for row {row} since {sha[:12]}: {reason}; rerun it (`force=true`)."
                    )
            sel = sel[~has]
        if sel.empty:
            continue
        shown = ", ".join(files[:6]) + (f" and {len(files) - 6} more" if len(files) > 6 else "")
        dirty = any(c == f"{sha}-dirty" for c in counts.index)
        lines.append(
            f"**Code changed since {sha[:12]}**"
            + (" (some runs made with uncommitted changes on top)" if dirty else "")
            + f" in what its {len(sel)} run(s) without a fingerprint build: {shown}; their numbers may not "
            "be what the code gives today."
        )
    if "unknown" in counts.index:
        lines.append(f"{counts['unknown']} run(s) made by an ablate of unknown commit (not a git checkout).")
    if not targets:
        tail = ""
    elif not changed:
        tail = "; no code they build has changed since"
    elif checked and not any(line.startswith("**") for line in lines):
        # the same words whichever kernels recomputed them: the same records give the same bytes on any CPU
        tail = f"; the code they build changed since, and the fingerprints of all {checked} rows still match"
    else:
        tail = ""
    return [head + tail + ".", *mixed, *lines, *metric_changed(runs, targets)]


def metric_changed(runs: pd.DataFrame, targets: set[str]) -> list[str]:
    """A line per metric the runs' code builds whose evaluator today (:func:`evaluators`) is not the
    one some runs were scored with (their ``evaluator`` tag; none on runs made before the tag)."""
    used = runs["evaluator"].fillna("") if "evaluator" in runs else pd.Series([""] * len(runs), dtype=str)
    lines = []
    for module, current in (evaluators(targets) if targets else {}).items():
        off = used[[current not in tag.split(", ") for tag in used]]
        if off.empty:
            continue
        counts = off.value_counts().sort_index()
        was = ", ".join(f"{tag or 'no recorded evaluator'}: {n}" for tag, n in counts.items())
        lines.append(
            f"**Metric changed since these runs**: {module} now follows {current} "
            f"(ablate/metrics/__init__.py), and {len(off)} of {len(runs)} runs were scored otherwise ({was}); "
            "rerun them (`force=true`) to compare with the paper."
        )
    return lines
