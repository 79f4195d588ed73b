"""The direction of imports in ``ablate``: every edge goes down the layers, and no module imports itself back
through others. The imports are read from the source (:mod:`ast`), an import inside a function included."""

import ast
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent / "ablate"
#: Lower layers first; a module may import from a lower layer or from its own piece, never from a higher one or a
#: sibling of its layer. Above the tasks: the store (MLflow), the tables (runs in, tables out), running one job
#: (``jobs``), what is read from trained runs afterwards (``analysis``: latency, the reproduction check, the
#: diagnosis), then the sweep (its callback and progress) and the capacity planning for the paper scale, side by
#: side, and the commands on top. The commands' argument parsing (``ablate.cli``: argparse only) is at the bottom,
#: for the commands and for the functions under them that do their work. The root package (``ablate/__init__.py``:
#: the version, the config resolvers) is beside them.
LAYERS = [
    ["ablate.hardware", "ablate.config", "ablate.options", "ablate.cli"],
    ["ablate.data"],
    ["ablate.nn", "ablate.metrics"],
    ["ablate.fusion"],
    ["ablate.tasks"],
    ["ablate.store"],
    ["ablate.tables"],
    ["ablate.jobs"],
    ["ablate.analysis"],
    ["ablate.sweep", "ablate.capacity"],
    ["ablate.__main__", "ablate.report", "ablate.latency", "ablate.diagnose", "ablate.check_paper"],
]
RANK = {piece: i for i, layer in enumerate(LAYERS) for piece in layer}


def modules() -> dict[str, Path]:
    out = {}
    for path in ROOT.rglob("*.py"):
        parts = list(path.relative_to(ROOT.parent).with_suffix("").parts)
        out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return out


def imports(name: str, path: Path, known: dict[str, Path]) -> set[str]:
    """The ``ablate`` modules ``name`` imports (``from pkg import module`` as the module, ``from mod import x`` as
    ``mod``)."""
    package = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            module = node.module or ""
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                module = ".".join(base + ([module] if module else []))
            found |= {f"{module}.{a.name}" if f"{module}.{a.name}" in known else module for a in node.names}
    return {m for m in found if m in known and m != name}


def piece(module: str) -> str:
    """The layer piece of a module: ``ablate.store.tracker`` -> ``ablate.store``."""
    return ".".join(module.split(".")[:2])


def graph() -> dict[str, set[str]]:
    known = modules()
    return {name: imports(name, path, known) for name, path in known.items()}


def test_every_module_belongs_to_a_layer():
    assert {piece(m) for m in graph()} - {"ablate"} <= set(RANK)


def test_imports_go_down_the_layers_only():
    wrong = []
    for a, targets in graph().items():
        for b in targets:
            pa, pb = piece(a), piece(b)
            if pa == pb or pb == "ablate":  # within a piece; the root package's version
                continue
            if pa == "ablate":  # the root's resolvers: ablate.hardware, and the modalities of ablate.data
                ok = pb in ("ablate.hardware", "ablate.data")
            else:
                ok = RANK[pb] < RANK[pa]
            if not ok:
                wrong.append(f"{a} -> {b}")
    assert not wrong, "imports against the layering: " + ", ".join(sorted(wrong))


def test_no_module_imports_itself_back_through_others():
    g, cycles, index, low, stack, on, counter = graph(), [], {}, {}, [], set(), [0]

    def visit(v):  # Tarjan's strongly connected components
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in g[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                cycles.append(sorted(comp))

    for v in sorted(g):
        if v not in index:
            visit(v)
    assert not cycles, f"import circles: {cycles}"


def test_the_checker_sees_an_upward_edge(tmp_path):
    """The parser finds a function-level import, relative or absolute (a check that can fail)."""
    known = {"ablate.store.x": tmp_path / "x.py", "ablate.jobs.job": tmp_path / "job.py", "ablate.jobs": tmp_path}
    src = tmp_path / "x.py"
    src.write_text("def f():\n    from ablate.jobs import job\n")
    assert imports("ablate.store.x", src, known) == {"ablate.jobs.job"}


@pytest.mark.parametrize(
    "package", ["ablate.store", "ablate.tables", "ablate.jobs", "ablate.analysis", "ablate.sweep", "ablate.capacity"]
)
def test_each_room_imports_alone(package):
    subprocess.run([sys.executable, "-c", f"import {package}"], check=True, timeout=120)


@pytest.mark.parametrize("module", ["ablate.__main__", "ablate.report", "ablate.store", "ablate.tables"])
def test_a_process_that_trains_nothing_does_not_import_lightning(module):
    # Lightning (and torch through it) takes seconds to import: a report, a bad option or the sweeper need none of it
    code = f"import sys, {module}; sys.exit('lightning' in sys.modules or 'torch' in sys.modules)"
    assert subprocess.run([sys.executable, "-c", code], timeout=120).returncode == 0


def test_a_report_with_no_fingerprint_to_recompute_imports_neither_lightning_nor_torch(tmp_path):
    # the report reads tuning rungs and curves (ablate.jobs.rungs, through the reproduction check's job specs): that
    # once imported Lightning, 5 s of an 8-s report of a table without records (AMD EPYC family 25 model 17)
    code = (
        "import runpy, sys\n"
        "sys.argv = ['ablate.report', 'experiment=chinet_table2']\n"
        "try:\n"
        "    runpy.run_module('ablate.report', run_name='__main__')\n"
        "except SystemExit as end:\n"
        "    assert not end.code, end.code\n"
        "sys.exit(sorted({'lightning', 'torch'} & set(sys.modules)) or None)"
    )
    env = {k: v for k, v in os.environ.items() if k != "MLFLOW_TRACKING_URI"}
    env["PYTHONPATH"] = str(Path(__file__).resolve().parents[1])
    done = subprocess.run(
        [sys.executable, "-c", code], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 0, done.stderr[-2000:]
    assert "chinet_table2: no run records yet" in done.stdout
