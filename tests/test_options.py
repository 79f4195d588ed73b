"""A wrong option is one line naming it, before any run (ablate.options): drawn by Hypothesis on composed configs,
held against the checks where the options are read, through the racing sweeper, and once end to end."""

from __future__ import annotations

import ast
import importlib.util
import math
import os
import re
import subprocess
import sys
import typing
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest
from hydra.errors import HydraException
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from mlflow.tracking import MlflowClient
from omegaconf import DictConfig, OmegaConf, open_dict

from ablate import options
from ablate.config import CONF, compose
from ablate.options import RULES, Kind, OptionError, Rule, check

REPO = Path(__file__).resolve().parents[1]

#: Configs in which every option of the table has its parent: a road table at the paper's scale, tuned (BEV,
#: augmentation, a race, a rope), and a detection table of DGFN's model on DDP (the SSD trunks, GFU, a strategy).
BASES = (
    ["experiment=bifnet_table4", "row=bifnet_dst_cbf", "scale=paper", "tune=lr_wd_halving"],
    ["experiment=dgfn_table1", "row=dgfn", "trainer=ddp_cpu", "+task.metric.devkit=2d_2012"],
)
#: The Python types of each kind's values, as a test tells them apart: a boolean is no number, whatever Python says.
TYPES = {
    "bool": {bool},
    "int": {int},
    "number": {int, float},
    "str": {str},
    "dir": {str},
    "place": {str},
    "mapping": {dict},
    "list": {list},
    "ints": {list},
    "numbers": {list},
    "strs": {list},
}
SPACE = {"task.optimizer.lr": "tag(log, interval(1e-4, 1e-2))"}
#: Text that stays text in a config: no interpolation (``$``), no missing value (``???``).
TEXT = st.text(alphabet="abcdefgh_-. 0123456789XYZ", max_size=12)
VALUES = {
    bool: st.booleans(),
    int: st.integers(-(10**12), 10**12),
    float: st.floats(allow_nan=False, width=32),
    str: TEXT,
    dict: st.dictionaries(st.sampled_from("abc"), st.integers(0, 3), max_size=2),
    list: st.lists(st.integers(-3, 3), max_size=3),
    type(None): st.none(),
}


@pytest.fixture(scope="module")
def launch(tmp_path_factory) -> Path:
    """A launch directory, with a folder a ``data.root`` may name, a file it may not, and a link to nothing, where
    ``data.data_dir`` cannot make its folder."""
    folder = tmp_path_factory.mktemp("launch")
    (folder / "kitti").mkdir()
    (folder / "a_file").write_text("not a folder")
    (folder / "a_link").symlink_to(folder / "gone")
    return folder


class Bases(list):
    """The composed :data:`BASES` (a failing example names them, not their every value)."""

    def __repr__(self) -> str:
        return f"Bases({BASES})"


@pytest.fixture(scope="module")
def bases() -> list[DictConfig]:
    return Bases(compose(overrides) for overrides in BASES)


def base_for(bases: list[DictConfig], key: str) -> DictConfig:
    """The first base in which ``key``'s parent is a mapping (the first base where none has it)."""
    head = key.rpartition(".")[0]
    return next((b for b in bases if not head or isinstance(OmegaConf.select(b, head), DictConfig)), bases[0])


@contextmanager
def given_option(cfg: DictConfig, key: str, value: object) -> Iterator[DictConfig]:
    """``cfg`` with ``key`` set to ``value`` as an override would set it (an interpolated parent made concrete, a
    missing one added), then as it was: each example mutates the composed config, not a composition of its own."""
    top, parts, had = key.split(".")[0], key.split("."), key.split(".")[0] in cfg
    saved = OmegaConf.to_container(cfg, resolve=False)[top] if had else None
    with open_dict(cfg):
        node = cfg
        for part in parts[:-1]:
            child = node.get(part) if part in node else None
            if not isinstance(child, DictConfig) or OmegaConf.is_interpolation(node, part):
                node[part] = OmegaConf.to_container(child, resolve=True) if isinstance(child, DictConfig) else {}
            node = node[part]
        node[parts[-1]] = value
        try:
            yield cfg
        finally:
            if had:
                cfg[top] = saved
            else:
                del cfg[top]


def wrong_types(rule: Rule) -> st.SearchStrategy:
    """A value of a type none of the rule's kinds is of (null where null is not taken)."""
    taken = {t for kind in rule.kinds for t in (TYPES[kind.type] if kind.type else {type(v) for v in kind.values})}
    taken |= {type(None)} if rule.null else set()
    return st.sampled_from(sorted((t for t in VALUES if t not in taken), key=str)).flatmap(lambda t: VALUES[t])


def numbers(kind: Kind, good: bool) -> st.SearchStrategy:
    """Numbers of an int or number kind inside its range (``good``), or outside it (NaN among them)."""
    low, high, strict = kind.low, kind.high, kind.strict
    lo = None if low is None else (math.floor(low) + 1 if strict else math.ceil(low))
    hi = None if high is None else (math.ceil(high) - 1 if strict else math.floor(high))
    whole = st.integers(lo, hi) if lo is None or hi is None or lo <= hi else st.nothing()
    if good:
        if kind.type.startswith("int"):
            return whole
        return whole | st.floats(
            low,
            high,
            exclude_min=strict and low is not None,
            exclude_max=strict and high is not None,
            allow_nan=False,
            width=32,
        )
    floats = not kind.type.startswith("int")
    outside = [st.just(math.nan)] if floats else []
    if lo is not None:  # below the low bound (at it, where the bound is excluded)
        outside += [st.integers(max_value=lo - 1)]
        outside += [st.floats(max_value=low, exclude_max=not strict, width=32)] if floats else []
    if hi is not None:
        outside += [st.integers(min_value=hi + 1)]
        outside += [st.floats(min_value=high, exclude_min=not strict, width=32)] if floats else []
    return st.one_of(*outside)


def good_values(rule: Rule, launch: Path) -> st.SearchStrategy:
    """Values the rule says the option takes."""
    return st.one_of(*(good_value(kind, launch) for kind in rule.kinds), *([st.none()] if rule.null else []))


def good_value(kind: Kind, launch: Path) -> st.SearchStrategy:
    if not kind.type or (kind.type == "str" and kind.values):
        return st.sampled_from(kind.values)
    if kind.type in ("int", "number"):
        return numbers(kind, good=True)
    if kind.type == "str":
        return (
            st.from_regex(kind.pattern, fullmatch=True) if kind.pattern else TEXT.filter(lambda t: t or not kind.filled)
        )
    if kind.type == "dir":
        return st.sampled_from([str(launch / "kitti"), "kitti", "."])
    if kind.type == "place":
        return st.sampled_from([str(launch / "kitti"), "kitti", "missing", str(launch / "missing" / "data")])
    if kind.type == "mapping":
        return st.just(dict(SPACE)) if kind.filled else st.just({})
    if kind.type in ("bool", "list"):
        return st.booleans() if kind.type == "bool" else VALUES[list]
    items = {"ints": numbers, "numbers": numbers}.get(kind.type)
    item = items(kind, True) if items else (st.sampled_from(kind.values) if kind.values else TEXT.filter(bool))
    lists = st.lists(item, min_size=kind.size or int(kind.filled), max_size=kind.size or 4, unique=kind.order == "<")
    return lists.map(sorted) if kind.order else lists


def out_of_range(rule: Rule, launch: Path) -> st.SearchStrategy:
    """Values of a type the option takes but outside what it takes: a number past its bounds, a name not among its
    choices, a list empty, of the wrong size, out of order or with one item wrong, a file for a folder."""
    if len(rule.kinds) > 1:
        return st.nothing()
    (kind,) = rule.kinds
    if kind.type in ("int", "number"):
        return numbers(kind, good=False)
    if not kind.type or (kind.type == "str" and kind.values):
        return TEXT.filter(lambda t: t not in kind.values)
    if kind.type == "str":
        unmatched = TEXT.filter(lambda t: not re.fullmatch(kind.pattern, t)) if kind.pattern else st.nothing()
        return unmatched | (st.just("") if kind.filled else st.nothing())
    if kind.type == "dir":
        return st.sampled_from([str(launch / "a_file"), "a_file", str(launch / "missing"), ""])
    if kind.type == "place":
        return st.sampled_from([str(launch / "a_file"), "a_file", "a_link", str(launch / "a_link"), ""])
    if kind.type in ("ints", "numbers", "strs"):
        good = good_value(kind, launch).filter(bool)
        bad_item = (
            numbers(kind, False) if kind.type != "strs" else TEXT.filter(lambda t: kind.values and t not in kind.values)
        )
        one_wrong = st.tuples(good, bad_item).map(lambda g: [*g[0][:-1], g[1]])
        shapes = [one_wrong]
        shapes += [st.just([])] if kind.filled else []
        shapes += [good.map(lambda v: [*v, v[-1]])] if kind.size or kind.order == "<" else []
        shapes += [good.filter(lambda v: len(set(v)) > 1).map(lambda v: v[::-1])] if kind.order else []
        return st.one_of(*shapes)
    if kind.type == "mapping":
        unknown = st.just({"not_an_option": 1}) if rule.keys else st.nothing()
        return unknown | (st.just({}) if kind.filled else st.nothing())
    return st.nothing()


def bad_values(rule: Rule, launch: Path) -> st.SearchStrategy:
    return wrong_types(rule) | out_of_range(rule, launch)


def drawn(values) -> st.SearchStrategy:
    """An option of the table and a value for it from ``values(rule)``."""
    return st.sampled_from(sorted(RULES)).flatmap(lambda key: st.tuples(st.just(key), values(RULES[key])))


@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data())
def test_a_wrong_value_of_any_option_is_one_error_naming_it(data, bases, launch):
    key, value = data.draw(drawn(lambda rule: bad_values(rule, launch)))
    with given_option(base_for(bases, key), key, value) as cfg, pytest.raises(OptionError) as refused:
        check(cfg, launch)
    message = str(refused.value)
    assert "\n" not in message
    if RULES[key].keys and isinstance(value, dict) and value:  # an option the mapping does not have
        assert message.startswith(f"{key}.not_an_option: not an option of {key}, which takes ")
    else:  # the value given and what the option takes
        assert message.startswith(f"{key}: {'null' if value is None else repr(value)} must be ")
        assert options.accepts(RULES[key]) in message


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data())
def test_a_good_value_of_any_option_passes(data, bases, launch):
    key, value = data.draw(drawn(lambda rule: good_values(rule, launch)))
    with given_option(base_for(bases, key), key, value) as cfg:
        check(cfg, launch)


def test_the_bases_pass_and_hold_the_parent_of_every_option(bases, launch):
    """The properties set each option where an override would: in a mapping that a composed config has."""
    for cfg in bases:
        check(cfg, launch)
    parents = {k.rpartition(".")[0] for k in RULES} - {""}
    assert [p for p in sorted(parents) if not any(isinstance(OmegaConf.select(b, p), DictConfig) for b in bases)] == []


def consumers() -> dict[str, tuple[typing.Callable[[dict], object], dict]]:
    """The checks where a mapping of options is read, and a good mapping of it: the racing plan, the tuning phase
    and the numerics."""
    from ablate import hardware
    from ablate.sweep.tuning import TuneSpec
    from ablate.tables.racing import RacePlan

    return {
        "table.seeds": (RacePlan.from_config, {"looks": [3, 5]}),
        "table.tune": (TuneSpec.from_config, {"trials": 3, "space": SPACE}),
        "trainer": (lambda t: hardware.check(OmegaConf.create(t)), {"threads": 1, "channels_last": "auto"}),
    }


CONSUMED = {
    "table.seeds": ("looks", "alpha", "correction", "budget_min", "multiplicity"),
    "table.tune": ("trials", "budget_min", "experts"),
    "trainer": ("threads", "channels_last"),
}


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data())
def test_what_the_checks_where_options_are_read_refuse_is_refused_first(data, bases, launch):
    """Each value the racing plan, the tuning phase or the numerics would refuse once a job or a sweep has started
    is refused before, naming the same option: the table is never looser than they are."""
    section = data.draw(st.sampled_from(sorted(CONSUMED)))
    option = data.draw(st.sampled_from(CONSUMED[section]))
    key = f"{section}.{option}"
    value = data.draw(good_values(RULES[key], launch) | bad_values(RULES[key], launch))
    read, good = consumers()[section]
    try:
        read({**good, option: value})
        refused_later = False
    except (ValueError, TypeError):
        refused_later = True
    with given_option(base_for(bases, key), section, {**good, option: value}) as cfg:
        try:
            check(cfg, launch)
            refused_now = ""
        except OptionError as err:
            refused_now = str(err)
    if refused_later:
        assert refused_now.startswith(key), (value, refused_now)


def literal(path: Path, name: str) -> typing.Any:
    """The value of the constant ``name`` in the Python file ``path``, read without importing it (torch)."""
    for node in ast.parse(path.read_text()).body:
        targets = (
            node.targets if isinstance(node, ast.Assign) else [node.target] if isinstance(node, ast.AnnAssign) else []
        )
        if any(isinstance(t, ast.Name) and t.id == name for t in targets) and node.value is not None:
            if isinstance(node.value, ast.Subscript):  # Literal["a", "b"]
                return ast.literal_eval(node.value.slice)
            return ast.literal_eval(node.value)
    raise AssertionError(f"{name} not in {path}")


def test_the_choices_are_those_of_the_code_that_reads_them():
    from ablate.data.conditions import CONDITIONS
    from ablate.data.lidar_weather import LIDAR_WEATHER
    from ablate.tables.racing import RacePlan
    from ablate.tables.verdicts import MULTIPLICITY

    package = Path(options.__file__).parent
    assert options.DEVKITS == tuple(literal(package / "metrics" / "kitti.py", "DEVKITS"))
    assert options.ON_BAD_FRAME == literal(package / "data" / "datamodule.py", "ON_BAD_FRAME")
    assert options.MODALITIES == tuple(literal(package / "data" / "dataset.py", "MODALITIES"))
    assert (options.CONDITIONS, options.LIDAR_WEATHER) == (tuple(CONDITIONS), tuple(LIDAR_WEATHER))
    assert options.MULTIPLICITY == MULTIPLICITY
    assert options.CORRECTIONS == sys.modules[RacePlan.__module__].CORRECTIONS  # where the plan is defined
    spec = importlib.util.find_spec("lightning")
    assert spec is not None and spec.origin is not None
    precision = Path(spec.origin).parent / "fabric" / "plugins" / "precision" / "precision.py"
    names = ("_PRECISION_INPUT_STR", "_PRECISION_INPUT_STR_ALIAS", "_PRECISION_INPUT_INT")
    lightning = {value for name in names for value in literal(precision, name)}
    assert set(options.PRECISIONS) - {"auto"} == lightning


def refused_sweep(overrides: list[str], swept: list[str], launch: Path, monkeypatch) -> int:
    """The racing sweeper's sweep of ``swept`` over the config of ``overrides``: the status it ends with, having
    opened no parent run and launched no job."""
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir

    import hydra_plugins.ablate_racing_sweeper._impl as impl
    from hydra_plugins.ablate_racing_sweeper.racing_sweeper import RacingSweeper

    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        config = hydra_compose("config", overrides=overrides, return_hydra_config=True)
    config.hydra.runtime.cwd, config.hydra.sweep.dir = str(launch), "sweep"
    opened, launched = [], []
    monkeypatch.setattr(impl, "open_parent", lambda cfg: opened.append(cfg))
    sweeper = RacingSweeper(params=dict(config.hydra.sweeper.params or {}))
    launcher = type("Launcher", (), {"launch": lambda self, jobs, initial_job_idx: launched.append(jobs) or []})()
    sweeper.sweeper.config, sweeper.sweeper.launcher = config, launcher
    sweeper.sweeper.hydra_context = type("Context", (), {"config_loader": None})()
    with pytest.raises(SystemExit) as ended:
        sweeper.sweep(swept)
    assert opened == [] and launched == []
    return int(ended.value.code)


def test_a_sweep_refuses_a_wrong_swept_value_before_its_parent_run_and_its_first_job(tmp_path, monkeypatch, capsys):
    assert refused_sweep(["experiment=chinet_table2"], ["scale.race.alpha=0.05,1.5"], tmp_path, monkeypatch) == 1
    assert capsys.readouterr().err.strip() == (
        f"error: scale.race.alpha: 1.5 must be {options.accepts(RULES['scale.race.alpha'])}"
    )


KITTI_WITHOUT_ROOT = "data.root: data=kitti reads real KITTI from a path: give data.root=/path/to/kitti/object"


def test_real_kitti_without_a_root_is_refused_and_with_one_read(kitti_root, tmp_path, monkeypatch, capsys):
    """data=kitti cannot fall back on synth.yaml's ``root: null`` (the generated data): without data.root a job and
    a sweep end in one line naming it; with it, the data module reads the real frames and generates none. The
    generated data's configs do not hold the marker that kitti.yaml sets."""
    from hydra.utils import instantiate

    from ablate.data.datamodule import KittiDataModule

    for overrides in (["data=kitti"], ["data=kitti", "data.root=null"], ["experiment=dgfn_table1", "data=kitti"]):
        with pytest.raises(OptionError) as refused:
            check(compose(overrides), tmp_path)
        assert str(refused.value) == KITTI_WITHOUT_ROOT, overrides
    assert refused_sweep(["experiment=dgfn_table1", "data=kitti"], ["seed=0,1"], tmp_path, monkeypatch) == 1
    assert capsys.readouterr().err.strip() == f"error: {KITTI_WITHOUT_ROOT}"
    for data in ([], ["data=synth"]):
        cfg = compose(data)
        check(cfg, tmp_path)
        assert options.REAL_DATA not in cfg and cfg.data.root is None
    cfg = compose(["experiment=dgfn_table1", "data=kitti", f"data.root={kitti_root / 'object'}"])
    check(cfg, tmp_path)
    datamodule = instantiate(cfg.data, data_dir=str(tmp_path / "data"))
    assert isinstance(datamodule, KittiDataModule)
    assert datamodule.split_dir() == kitti_root / "object" / "training" and not (tmp_path / "data").exists()


def test_python_m_ablate_with_a_file_for_data_root_is_one_line_and_no_run(tmp_path):
    (tmp_path / "labels.txt").write_text("not a KITTI folder")
    store = f"sqlite:///{tmp_path / 'store.db'}"
    env = {**os.environ, "PYTHONPATH": str(REPO), "MLFLOW_TRACKING_URI": store, "HYDRA_FULL_ERROR": "0"}
    command = [sys.executable, "-m", "ablate", "scale=smoke", "data.root=labels.txt"]
    out = subprocess.run(command, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
    assert out.returncode == 1, out.stdout[-2000:] + out.stderr[-2000:]
    assert out.stderr.strip().splitlines() == [
        f"error: data.root: 'labels.txt' must be {options.accepts(RULES['data.root'])}"
    ]
    client = MlflowClient(store)
    assert client.search_runs([e.experiment_id for e in client.search_experiments()]) == []


def test_a_data_folder_left_as_a_link_to_nothing_is_one_line_naming_it(tmp_path):
    """A ``data`` link whose folder was removed (a store moved, a disk unmounted) is refused by name before any run,
    not met as a FileExistsError when the first job makes its dataset; a link to a folder is taken."""
    (tmp_path / "data").symlink_to(tmp_path / "elsewhere")
    with pytest.raises(OptionError) as refused:
        check(compose([]), tmp_path)
    assert str(refused.value) == f"data.data_dir: 'data' must be {options.accepts(RULES['data.data_dir'])}"
    assert "not a link to nothing" in str(refused.value)
    (tmp_path / "elsewhere").mkdir()
    check(compose([]), tmp_path)


def test_a_config_composed_again_is_the_same_and_a_callers_change_stays_its_own() -> None:
    first = compose(["experiment=chinet_table2", "seed=3"])
    first.seed = 99
    again = compose(["experiment=chinet_table2", "seed=3"])
    assert again.seed == 3 and OmegaConf.to_yaml(again) == OmegaConf.to_yaml(
        compose(["experiment=chinet_table2", "seed=3"])
    )
    assert compose(["experiment=chinet_table3"]).table.name == "chinet_table3"


def test_the_same_overrides_in_another_order_or_spelling_are_composed_once_and_a_key_set_twice_keeps_its_order(
    monkeypatch,
) -> None:
    """A sweep's jobs list their row first and say ``False``; the command line said ``false``: one config, composed
    once. Where the order matters (a key set twice, one inside another, a group appended) it is kept."""
    import ablate.config as config

    made = []
    real = config._canonical

    def counted(overrides):
        made.append(tuple(overrides))
        return real(overrides)

    monkeypatch.setattr(config, "_composed", type(config._composed)())
    monkeypatch.setattr(config, "_canonical", counted)
    first = compose(["experiment=chinet_table2", "publish=false", "row=unet", "++draws.task.optimizer.lr=1e-3"])
    assert len(config._composed) == 1
    again = compose(["row=unet", "experiment=chinet_table2", "++draws.task.optimizer.lr=0.001", "publish=False"])
    assert len(config._composed) == 1 and OmegaConf.to_yaml(again) == OmegaConf.to_yaml(first) and len(made) == 2
    assert compose(["seed=1", "seed=2"]).seed == 2 and compose(["seed=2", "seed=1"]).seed == 1
    assert len(config._composed) == 3
    inner = compose(["data.limit_frames={test:2}", "data.limit_frames.test=3"])
    assert inner.data.limit_frames.test == 3 and len(config._composed) == 4
    with pytest.raises(HydraException, match="data.limit_frames.test"):  # set before the dict it lies in: no key
        compose(["data.limit_frames.test=3", "data.limit_frames={test:2}"])
