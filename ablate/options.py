"""The options a user sets by hand (docs/config.md), checked on the composed config before any MLflow run exists.

One table, :data:`RULES`, says what each option accepts: one or more :class:`Kind` (a type, a range, choices, a
list's form), what null means where null is taken, and for a mapping the options it holds. :func:`check` reads each
option of the table that the config holds, parents before their options, and raises one :class:`OptionError` for
the first that breaks its rule; the message is one line naming its full dotted key, the value given and what it
accepts::

    trainer.threads: -1 must be a positive integer (or null: torch's default, every core)

``python -m ablate`` checks a job's config before it imports torch or opens the store (``ablate/__main__.py``), so a
mistake records no RUNNING or FAILED run; the racing sweeper checks the sweep's config and each value it sweeps
(:func:`check_sweep`) before its parent run and its first job. The checks where the options are read stay.
"""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence
from copy import deepcopy
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, ListConfig, OmegaConf, open_dict
from omegaconf.errors import OmegaConfBaseException, ValidationError


class OptionError(ValidationError):
    """An option with a value it does not take, in one line naming it; a ValueError and an OmegaConf error alike."""


@dataclass(frozen=True)
class Kind:
    """One kind of value an option accepts. ``type``: bool, int, number, str, dir (an existing directory, relative
    to the launch directory), place (a directory, or a path where one can be made), mapping, list, or ints / numbers
    / strs (a list of those); empty: only ``values``. ``low`` / ``high`` bound a number, or each number of a list
    (``strict``: the bounds themselves excluded); ``values``: the only values taken (each item's, for strs);
    ``pattern`` (regex) and ``says`` (how a message names it): a string's form; ``size``, ``order`` (``<``
    increasing strictly, ``<=`` never decreasing) and ``filled`` (not empty): a list's or a string's form."""

    type: str = ""
    low: float | None = None
    high: float | None = None
    strict: bool = False
    values: tuple[Any, ...] = ()
    pattern: str = ""
    says: str = ""
    size: int | None = None
    order: str = ""
    filled: bool = False


@dataclass(frozen=True)
class Rule:
    """What one option accepts: any of ``kinds``; null where ``null`` says what it means; ``note``: why, after
    what it accepts; ``keys``: a mapping's options (any other is refused); ``needed``: a marker key and what to
    say where the config holds it (true): the option must then be given, null or absent refused."""

    kinds: tuple[Kind, ...]
    null: str = ""
    note: str = ""
    keys: tuple[str, ...] = ()
    needed: tuple[str, str] | None = None


BOOL = Kind("bool")
WHOLE = Kind("int", low=0)  # a count or a seed
POSITIVE_INT = Kind("int", low=1)
POSITIVE = Kind("number", low=0, strict=True)
NON_NEGATIVE = Kind("number", low=0)
NAME = Kind("str", filled=True)
TEXT = Kind("str")
AUTO = Kind(values=("auto",))
MAPPING = Kind("mapping")
#: Names that become files and MLflow experiments (a table's): letters, digits, '_', '.', '-'.
FILE_NAME = Kind("str", pattern=r"[\w.-]+", says="a name of letters, digits, '_', '.', '-'")
DEVICE = Kind("str", pattern=r"auto|cpu|mps|cuda(:\d+)?", says="auto, cpu, mps, cuda or cuda:N")

#: What these options take where they are read, repeated here so that checking needs neither torch nor the store;
#: tests/test_options.py holds each to its source (the racing plan's corrections, ablate.metrics.kitti.DEVKITS,
#: ablate.data.dataset.MODALITIES, Lightning's precisions, ...).
CORRECTIONS = ("bonferroni", "pocock", "obrien_fleming", "none")
MULTIPLICITY = ("holm", "bh", "none")
DEVKITS = ("2017", "2d_2012")
ON_BAD_FRAME = ("error", "skip")
CONDITIONS = ("clear", "night", "rain_day", "rain_night", "glare")
LIDAR_WEATHER = ("clear", "rain", "fog")
MODALITIES = ("rgb", "intensity", "sparse_depth", "dense_depth", "ddm_jet", "dhi", "bev")
#: Lightning's precisions (its _PRECISION_INPUT), and auto (ablate.hardware.resolve).
PRECISIONS: tuple[str | int, ...] = (*"auto 32-true bf16-mixed 16-mixed 64-true bf16-true 16-true bf16".split(), 32, 64)
PRECISIONS += (16, "32", "64", "16", "transformer-engine", "transformer-engine-float16")
SEEDS_KEYS = ("looks", "alpha", "correction", "budget_min", "multiplicity")
SPLITS = ("train", "val", "test")
TUNE_KEYS = ("trials", "space", "seed", "budget_min", "job_seed", "experts", "halving")
#: The marker of a data config that reads real data from ``data.root`` (conf/data/kitti.yaml sets it, no other
#: config): ``data.root`` cannot stay synth.yaml's null there, which a missing value (``???``) would not replace.
REAL_DATA = "real_data"


def _race(prefix: str, null: str) -> dict[str, Rule]:
    """The rules of a race's plan (``table.seeds``, and ``scale.race``, which experiments take it from)."""
    return {
        prefix: Rule((Kind("mapping"),), null=null, keys=SEEDS_KEYS),
        f"{prefix}.looks": Rule((Kind("ints", low=1, filled=True, order="<"),), note="the seeds per row at each look"),
        f"{prefix}.alpha": Rule((Kind("number", low=0, high=1, strict=True),)),
        f"{prefix}.correction": Rule((Kind("str", values=CORRECTIONS),)),
        f"{prefix}.budget_min": Rule((POSITIVE,), null="no budget"),
        f"{prefix}.multiplicity": Rule((Kind("str", values=MULTIPLICITY),)),
    }


#: Every option a user sets by hand, by its full dotted key, parents before their options, and an option before
#: those that take its value (``table.seeds: ${scale.race}``): the one the user gave is named (docs/config.md).
RULES: dict[str, Rule] = {
    "seed": Rule((WHOLE,)),
    "force": Rule((BOOL,)),
    "publish": Rule((BOOL,)),
    "plan.measure_s": Rule((NON_NEGATIVE,), note="0: no timing"),
    "trace.every": Rule((POSITIVE_INT,), null="no trace"),
    "experts": Rule((MAPPING,), null="trains end to end"),
    "experts.freeze": Rule((BOOL,)),
    "experts.cache_features": Rule((BOOL,)),
    "experts.cache_max_gb": Rule((NON_NEGATIVE,), null="no bound"),
    "experts.max_epochs": Rule((POSITIVE_INT,), null="the job's"),
    "comp_time.warmup": Rule((WHOLE,)),
    "comp_time.repeats": Rule((POSITIVE_INT,)),
    "comp_time.threads": Rule((POSITIVE_INT,)),
    "comp_time.device": Rule((DEVICE,)),
    "comp_time.after_sweep": Rule((BOOL,)),
    "modalities": Rule((Kind("strs", values=MODALITIES, filled=True),)),
    "primary": Rule((NAME,)),
    "metrics": Rule((MAPPING,)),
    **_race("scale.race", "no race"),
    "scale.width": Rule((POSITIVE,)),
    "scale.fpn_channels": Rule((POSITIVE_INT,)),
    "scale.unet_widths": Rule((Kind("ints", low=1, filled=True),)),
    "table.name": Rule((FILE_NAME,), note="it names the MLflow experiment and the table's files"),
    "table.title": Rule((TEXT,)),
    "table.primary": Rule((NAME,), null="the task's"),
    "table.metrics": Rule((MAPPING,), null="the task's"),
    "table.rows": Rule((Kind("list"),)),
    "table.reference": Rule((NAME, Kind("strs", filled=True)), null="the first row"),
    "table.rope": Rule((MAPPING,), null="no region of equivalence", keys=("delta", "reason", "follows")),
    "table.rope.delta": Rule((POSITIVE,), null="no region of equivalence"),
    "table.rope.reason": Rule((TEXT,), null="none given"),
    "table.rope.follows": Rule((NAME,), null="its own δ", note="the table whose δ it takes"),
    **_race("table.seeds", "every swept job at once"),
    # conf/tune/lr_wd.yaml reads it with oc.select, whose default (8) stands in for a missing key only: null is not 8
    "table.tune_trials": Rule((POSITIVE_INT,), note="the family's N of tune=lr_wd; leave it out for 8"),
    "table.tune_halving": Rule(
        (MAPPING,),
        null="every trial to the full budget",
        keys=("eta", "rungs"),
        note="the table's default of tune=lr_wd",
    ),
    "table.tune": Rule((MAPPING,), null="no tuning phase", keys=TUNE_KEYS),
    "table.tune.trials": Rule((POSITIVE_INT,), note="trial 0 is the recipe"),
    "table.tune.space": Rule((Kind("mapping", filled=True),), note="parameter -> interval(...) or choice(...)"),
    "table.tune.seed": Rule((WHOLE,)),
    "table.tune.budget_min": Rule((POSITIVE,), null="no budget"),
    "table.tune.job_seed": Rule((WHOLE,)),
    "table.tune.experts": Rule((BOOL,)),
    "table.tune.halving": Rule((MAPPING,), null="every trial to the full budget", keys=("eta", "rungs")),
    "table.tune.halving.eta": Rule((Kind("int", low=2),), note="the top 1/eta of a rung go on"),
    "table.tune.halving.rungs": Rule((Kind("numbers", low=0, high=1, filled=True, order="<"),), note="the last 1"),
    "rung": Rule((Kind("number", low=0, high=1, strict=True),), null="the full budget", note="set by the sweeper"),
    "table.tuned_from": Rule((Kind("str", values=("published",)),), null="the recipe, or the table's tuning phase"),
    "table.kernels_sd": Rule((NON_NEGATIVE,), null="not measured"),
    "table.kernels_run": Rule((MAPPING,), null="not measured", keys=("sd", "seeds")),
    "table.kernels_run.sd": Rule((NON_NEGATIVE,), note="a rerun's shift on other numerics, root mean square"),
    "table.kernels_run.seeds": Rule((POSITIVE_INT,), note="the seeds whose reruns measured it"),
    "table.untuned": Rule((TEXT,), null="the table tunes, or says nothing"),
    "data.root": Rule(
        (Kind("dir"),),
        null="the generated data",
        note="KITTI's, relative to the launch directory",
        needed=(REAL_DATA, "data=kitti reads real KITTI from a path: give data.root=/path/to/kitti/object"),
    ),
    "data.data_dir": Rule((Kind("place"),), note="where the generated data are kept, relative to the launch directory"),
    "data.batch_size": Rule((POSITIVE_INT,)),
    "data.num_workers": Rule((WHOLE,)),
    "data.memo_gb": Rule((NON_NEGATIVE,), note="GiB a split keeps in memory between epochs; 0: off"),
    "data.seed": Rule((WHOLE,)),
    "data.order_seed": Rule((WHOLE,)),
    **{f"data.synth.{size}": Rule((POSITIVE_INT,)) for size in ("frames", "height", "width")},
    "data.synth.seed": Rule((WHOLE,)),
    "data.synth.furniture": Rule((BOOL,), note="street furniture in every scene (ablate.data.synth)"),
    "data.conditions": Rule((Kind("strs", values=CONDITIONS, filled=True),)),
    "data.lidar_weather": Rule((Kind("strs", values=LIDAR_WEATHER, filled=True),), null="no weather"),
    "data.severity": Rule((NON_NEGATIVE,), note="1: the defaults, 0: no change"),
    "data.max_depth": Rule((POSITIVE,)),
    "data.limit_frames": Rule((MAPPING,), null="every frame", keys=SPLITS, note="split -> frames"),
    **{f"data.limit_frames.{split}": Rule((WHOLE,), null="every frame") for split in SPLITS},
    "data.on_bad_frame": Rule((Kind("str", values=ON_BAD_FRAME),)),
    "data.bev.cell": Rule((POSITIVE,)),
    "data.bev.window": Rule((WHOLE,), note="px"),
    "data.bev.azimuth_res": Rule((POSITIVE,), note="degrees"),
    "data.bev.max_points": Rule((POSITIVE_INT,)),
    "data.augment": Rule((MAPPING,), null="no augmentation", keys=("flip", "scale", "photometric")),
    "data.augment.flip": Rule((Kind("number", low=0, high=1),), note="a probability"),
    "data.augment.photometric": Rule((Kind("number", low=0, high=1),), note="a probability per step; 0: off"),
    "data.augment.scale": Rule((Kind("numbers", low=1, size=2, order="<="),), note="[lo, hi], zoom in only"),
    "task.metric": Rule((MAPPING,), null="the metric's defaults"),
    "task.metric.devkit": Rule((Kind("str", values=DEVKITS),)),
    "task.eval_conditions": Rule((MAPPING,), null="the test data as it is"),
    "task.eval_severities": Rule((Kind("numbers", low=0, strict=True),)),
    "stage.space": Rule((NAME,), note="a registered space transform: dst, shpl, ..."),
    "fusion.gated": Rule((BOOL,)),
    "model.single": Rule((Kind("str", values=MODALITIES),), null="every modality, fused"),
    "model.input_size": Rule((Kind("ints", low=1, size=2),), note="[height, width]"),
    "model.l2norm_scale": Rule((POSITIVE,)),
    "model.batch_norm": Rule((BOOL,)),
    "model.blank_running_stats": Rule((BOOL,)),
    "logger.tracking_uri": Rule((NAME,)),
    "logger.artifact_root": Rule((NAME,), null="beside the store"),
    "logger.log_checkpoint": Rule((BOOL,)),
    "logger.log_figures": Rule((BOOL,)),
    "logger.system_metrics": Rule((BOOL,)),
    "logger.outage_s": Rule((NON_NEGATIVE,), note="seconds"),
    "trainer.accelerator": Rule((Kind("str", values=("auto", "cpu", "gpu", "cuda", "mps")),)),
    "trainer.devices": Rule((POSITIVE_INT, Kind(values=(-1, "auto")), Kind("ints", low=0, filled=True))),
    "trainer.max_epochs": Rule((POSITIVE_INT, Kind(values=(-1,)))),
    "trainer.enable_progress_bar": Rule((BOOL, AUTO)),
    **{f"trainer.limit_{split}_batches": Rule((Kind("number", low=0, high=1), WHOLE)) for split in SPLITS},
    "trainer.precision": Rule((Kind(values=PRECISIONS),)),
    "trainer.channels_last": Rule((BOOL, AUTO)),
    "trainer.compile": Rule((BOOL, Kind("str", filled=True, says="a backend's name")), note="true: inductor"),
    "trainer.threads": Rule((POSITIVE_INT,), null="torch's default, every core"),
    "trainer.gradient_clip_val": Rule((POSITIVE,), null="no clipping"),
    "trainer.gradient_clip_algorithm": Rule((Kind("str", values=("norm", "value")),)),
    "trainer.strategy.find_unused_parameters": Rule((BOOL,)),
}


def check(cfg: DictConfig, launch_dir: Path | None = None) -> None:
    """Raise one :class:`OptionError` for the first option of :data:`RULES` in ``cfg`` whose value its rule does not
    take; an option whose parent is absent or null is not there to check. ``launch_dir``: where a relative
    ``data.root`` is (the current directory where None). Only the options' own values are resolved (the model's
    ``${channels:...}`` would import torch)."""
    nodes: dict[str, Any] = {"": cfg}
    for key, rule in RULES.items():
        _given(nodes, key, rule)
        found, value = _lookup(nodes, key)
        if found:
            _check_one(key, value, rule, launch_dir or Path.cwd())


def check_sweep(config: DictConfig, arguments: Sequence[str], params: Mapping[str, Any] | None = None) -> None:
    """A sweep's options, before its parent run and its first job: its config (the command line's fixed values
    applied), then each value the sweep gives an option (``key=a,b`` on the command line, or in the sweeper's
    ``params``), set on a copy of it. A config group's choice (``fusion=sum,max``, a table's rows) is a file of
    ``conf/`` or the user's own: each job checks the config it composes (``ablate/__main__.py``) before its run."""
    from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
    from hydra.core.override_parser.overrides_parser import OverridesParser

    launch = Path(str(OmegaConf.select(config, "hydra.runtime.cwd", default=".")))
    check(config, launch)
    parser = OverridesParser.create()
    given = {f"{k}={v}": True for k, v in (params or {}).items()} | dict.fromkeys(arguments, False)
    groups = set(OmegaConf.select(config, "hydra.runtime.choices", default=None) or {})
    for override, param in zip(parser.parse_overrides(list(given)), given.values(), strict=True):
        key = override.get_key_element().lstrip("+~")
        if key in groups or override.is_delete() or not (param or override.is_sweep_override()):
            continue
        for (line,) in BasicSweeper.split_arguments([override], None)[0]:
            copy = deepcopy(config)
            with open_dict(copy):
                OmegaConf.update(copy, key, parser.parse_override(line).value(), merge=True, force_add=True)
            check(copy, launch)


#: What :func:`_lookup` finds where an option is not there (its parent absent, null or not a mapping; itself absent).
ABSENT = (False, None)
NOTHING = object()


def _node(nodes: dict[str, Any], path: str) -> Any:
    """The node at dotted ``path``, resolved (:data:`NOTHING` where it is not there), kept in ``nodes`` for the
    options under it; one that does not resolve is one OptionError naming it."""
    if path not in nodes:
        head, _, last = path.rpartition(".")
        parent = _node(nodes, head)
        nodes[path] = NOTHING
        if _has(parent, last) and not OmegaConf.is_missing(parent, last):
            try:
                nodes[path] = parent[last]
            except (OmegaConfBaseException, ValueError, TypeError) as err:
                raw = OmegaConf.to_container(parent, resolve=False)[last]  # type: ignore[index,call-overload]
                raise OptionError(f"{path}: {raw} does not resolve: {_first(err)}") from None
    return nodes[path]


def _lookup(nodes: dict[str, Any], key: str) -> tuple[bool, Any]:
    """``(True, value)`` of ``key``, resolved, a container as plain lists and dicts; :data:`ABSENT` where it is not
    there. A missing value (``???``: one the user must give) is one OptionError naming it."""
    head, _, last = key.rpartition(".")
    parent = _node(nodes, head)
    if _has(parent, last) and OmegaConf.is_missing(parent, last):
        raise OptionError(f"{key}: no value given (???); it must be {accepts(RULES[key])}")
    node = _node(nodes, key)
    if node is NOTHING:
        return ABSENT
    try:
        return True, OmegaConf.to_container(node, resolve=True) if isinstance(node, DictConfig | ListConfig) else node
    except (OmegaConfBaseException, ValueError, TypeError) as err:
        raise OptionError(f"{key}: a value in it does not resolve: {_first(err)}") from None


def _given(nodes: dict[str, Any], key: str, rule: Rule) -> None:
    """One OptionError where the config holds the marker of ``rule.needed`` (true) and ``key`` is null, missing
    (``???``) or absent: the option it cannot run without, and how to give it."""
    if rule.needed is None or _node(nodes, rule.needed[0]) is not True:
        return
    head, _, last = key.rpartition(".")
    parent = _node(nodes, head)
    if not _has(parent, last) or OmegaConf.is_missing(parent, last) or _node(nodes, key) is None:
        raise OptionError(f"{key}: {rule.needed[1]}")


def _has(node: Any, key: str) -> bool:
    """Whether a mapping node holds ``key``, a missing value (``???``) too; asked without an exception (OmegaConf
    raises and catches one for a key a struct config lacks)."""
    return isinstance(node, DictConfig) and key in node.keys()


def _first(err: BaseException) -> str:
    return (str(err).strip() or type(err).__name__).splitlines()[0]


def _check_one(key: str, value: Any, rule: Rule, launch: Path) -> None:
    if value is None and rule.null:
        return
    if not any(_takes(kind, value, launch) for kind in rule.kinds):
        strings = all(k.type == "str" or (k.values and all(isinstance(v, str) for v in k.values)) for k in rule.kinds)
        hint = f" (as text, quoted: {key}='{value}')" if strings and isinstance(value, int | float) else ""
        raise OptionError(f"{key}: {'null' if value is None else repr(value)} must be {accepts(rule)}{hint}")
    unknown = [str(k) for k in value if str(k) not in rule.keys] if rule.keys else []
    if unknown:
        raise OptionError(f"{key}.{unknown[0]}: not an option of {key}, which takes {', '.join(rule.keys)}")


def _takes(kind: Kind, value: Any, launch: Path) -> bool:
    """Whether ``value`` is of ``kind``: exact values of the same type (true is not 1, 32 is not '32'); no boolean
    is a number (YAML's true is Python's, a subclass of int); NaN is in no range."""
    if not kind.type:
        return any(type(value) is type(v) and value == v for v in kind.values)
    if kind.type in ("list", "ints", "numbers", "strs"):
        if not isinstance(value, list) or (kind.filled and not value) or kind.size not in (None, len(value)):
            return False
        items = kind.type == "list" or all(_takes(replace(kind, type=kind.type[:-1]), v, launch) for v in value)
        pairs = zip(value, value[1:], strict=False)
        return items and (not kind.order or all(a < b if kind.order == "<" else a <= b for a, b in pairs))
    if kind.type in ("int", "number"):
        if isinstance(value, bool) or not isinstance(value, int if kind.type == "int" else int | float):
            return False
        above = kind.low is None or (value > kind.low if kind.strict else value >= kind.low)
        return above and (kind.high is None or (value < kind.high if kind.strict else value <= kind.high))
    if kind.type in ("str", "dir", "place") and (
        not isinstance(value, str) or (kind.filled or kind.type in ("dir", "place")) and not value
    ):
        return False
    if kind.type == "str":
        return (not kind.values or value in kind.values) and (
            not kind.pattern or bool(re.fullmatch(kind.pattern, value))
        )
    if kind.type == "dir":
        return (launch / Path(value).expanduser()).is_dir()
    if kind.type == "place":  # a link to nothing, or a file, stops the folder being made there
        path = launch / Path(value).expanduser()
        return path.is_dir() or not (path.exists() or path.is_symlink())
    return isinstance(value, bool if kind.type == "bool" else dict) and (bool(value) or not kind.filled)


def _listed(values: tuple[Any, ...]) -> str:
    """Values as a message lists them: a string that an override would read as a number quoted (``'2017'``)."""
    return ", ".join(repr(v) if isinstance(v, str) and re.fullmatch(r"[-+]?[\d.]+", v) else str(v) for v in values)


def _bounded(kind: Kind, noun: str, plural: bool) -> str:
    """A number kind in words: ``an integer >= 0``, ``positive numbers``, ``a number in (0, 1)``."""
    article = "" if plural else ("an " if noun[0] in "aeiou" else "a ")
    nouns, low, high = (noun + "s" if plural else noun), kind.low, kind.high
    if high is None and ((low == 1 and noun == "integer" and not kind.strict) or (low == 0 and kind.strict)):
        return f"{'' if plural else 'a '}positive {nouns}"
    if low is not None and high is not None:
        return f"{article}{nouns} in {'(' if kind.strict else '['}{low:g}, {high:g}{')' if kind.strict else ']'}"
    if low is not None or high is not None:
        sign = (">" if low is not None else "<") + ("" if kind.strict else "=")
        return f"{article}{nouns} {sign} {low if low is not None else high:g}"
    return f"{article}{nouns}"


def phrase(kind: Kind, alone: bool = True) -> str:
    """What one kind accepts, in words; ``alone``: the option's only kind (``one of a, b`` rather than ``a, b``)."""
    if kind.says:
        return kind.says
    if not kind.type or (kind.type == "str" and kind.values):
        return ("one of " if alone and len(kind.values) > 1 else "") + _listed(kind.values)
    if kind.type in ("int", "number"):
        return _bounded(kind, "integer" if kind.type == "int" else "number", plural=False)
    if kind.type in ("ints", "numbers", "strs"):
        strs = f"names among {_listed(kind.values)}" if kind.values else "strings"
        items = strs if kind.type == "strs" else _bounded(kind, kind.type[:-1].replace("int", "integer"), True)
        form = ("non-empty " if kind.filled else "") + "list of " + (f"{kind.size} " if kind.size else "")
        return f"a {form}{items}" + {"<": ", increasing strictly", "<=": ", never decreasing"}.get(kind.order, "")
    words = {
        "bool": "true or false" if alone else "true, false",
        "dir": "an existing directory",
        "place": "a directory, or a path where one can be made (not a file, not a link to nothing)",
        "list": "a list",
    }
    return words.get(kind.type, ("a non-empty " if kind.filled else "a ") + kind.type.replace("str", "string"))


def accepts(rule: Rule) -> str:
    """What an option accepts, in words: its kinds, then what null means and why in brackets (``a positive integer
    (trial 0 is the recipe)``)."""
    words = [phrase(kind, alone=len(rule.kinds) == 1) for kind in rule.kinds]
    words[0] += f" of {', '.join(rule.keys)}" if rule.keys else ""
    text = words[0] if len(words) == 1 else ", ".join(words[:-1]) + " or " + words[-1]
    notes = [f"or null: {rule.null}"] * bool(rule.null) + [rule.note] * bool(rule.note)
    return text + (f" ({'; '.join(notes)})" if notes else "")
