"""Stale runs: the modules a run's config builds, their imports, and what changed since the run's commit."""

import subprocess

from ablate.tables.provenance import ROOT, dependencies, stale


def test_dependencies_follow_imports_from_the_config_targets():
    files = {str(p.relative_to(ROOT)) for p in dependencies({"ablate.tasks.instance.InstanceTask"})}
    assert "ablate/tasks/instance.py" in files
    assert "ablate/tasks/yolact/anchors.py" in files  # imported by instance.py
    assert "ablate/__init__.py" in files and "ablate/tasks/__init__.py" in files
    assert "ablate/report.py" not in files and "ablate/latency.py" not in files


def git(cwd, *args):
    return subprocess.run(["git", *args], cwd=cwd, check=True, capture_output=True, text=True).stdout.strip()


def test_a_change_to_an_imported_module_makes_runs_stale_and_others_do_not(tmp_path):
    pkg = tmp_path / "pkg"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "model.py").write_text("from pkg.layers import conv\n\nclass Net:\n    pass\n")
    (pkg / "layers.py").write_text("def conv():\n    return 1\n")
    (pkg / "report.py").write_text("import pkg.model\n")
    git(tmp_path, "init", "-q")
    git(tmp_path, "add", ".")
    git(tmp_path, "-c", "user.name=t", "-c", "user.email=t@t", "commit", "-qm", "one")
    sha = git(tmp_path, "rev-parse", "HEAD")
    targets = {"pkg.model.Net"}
    assert stale({sha}, targets, tmp_path, "pkg") == {}
    (pkg / "report.py").write_text("import pkg.model  # a table-only change\n")
    assert stale({sha}, targets, tmp_path, "pkg") == {}
    (pkg / "layers.py").write_text("def conv():\n    return 2\n")
    assert stale({sha}, targets, tmp_path, "pkg") == {sha: ["pkg/layers.py"]}
    assert stale({sha + "-dirty"}, targets, tmp_path, "pkg") == {sha + "-dirty": ["pkg/layers.py"]}
    assert stale({"0" * 40}, targets, tmp_path, "pkg") == {"0" * 40: ["unknown commit"]}


def test_a_package_on_the_way_counts_its_module_imports_not_its_re_exports(tmp_path):
    pkg = tmp_path / "pkg"
    (pkg / "nn").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "nn" / "__init__.py").write_text("from pkg.nn import registry\nfrom pkg.nn.vgg import VGG\n")
    for name in ("registry", "vgg", "unet", "chinet"):
        (pkg / "nn" / f"{name}.py").write_text("")
    (pkg / "nn" / "chinet.py").write_text("from pkg.nn.unet import Block\n")
    (pkg / "detector.py").write_text("from pkg.nn import VGG\n")
    files = lambda *t: {str(p.relative_to(tmp_path)) for p in dependencies(set(t), "pkg", tmp_path)}  # noqa: E731
    assert files("pkg.nn.chinet.build") == {
        "pkg/__init__.py",
        "pkg/nn/__init__.py",
        "pkg/nn/registry.py",
        "pkg/nn/chinet.py",
        "pkg/nn/unet.py",
    }
    assert "pkg/nn/vgg.py" in files("pkg.detector.Detector")  # names the package: its re-exports count
    assert "pkg/nn/vgg.py" in files("pkg.nn.chinet.build", "pkg.detector.Detector")
    real = {str(p.relative_to(ROOT)) for p in dependencies({"ablate.nn.chinet.build"})}
    assert "ablate/nn/unet.py" in real and "ablate/nn/vgg.py" not in real


def test_a_module_edited_while_the_process_runs_is_read_again(tmp_path):
    """The imports of each file are parsed once a process (a report asks for the same files for every table), but a
    file edited since is parsed again."""
    pkg = tmp_path / "pkg"
    pkg.mkdir()
    for name in ("__init__", "a", "b", "c"):
        (pkg / f"{name}.py").write_text("")
    (pkg / "a.py").write_text("from pkg.b import f\n")
    files = lambda: {p.name for p in dependencies({"pkg.a.run"}, "pkg", tmp_path)}  # noqa: E731
    assert files() == {"__init__.py", "a.py", "b.py"}
    (pkg / "a.py").write_text("from pkg.b import f\nfrom pkg.c import g\n")
    assert files() == {"__init__.py", "a.py", "b.py", "c.py"}
