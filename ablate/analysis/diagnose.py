"""Where fusion can gain over the single-modal experts, and where its gates look: ``python -m ablate.diagnose``.

SMoE's claim (seed 000 §5.1, Table 1) is that fusing the RGB and the DDM experts beats both. Whether it can on
given data depends on what the experts know that the other does not. For every seed of a two-stage table
(default ``experiment=smoe_table1``; any ``key=value`` override applies, e.g. ``scale=smoke``) this evaluates the
trained checkpoints on the test split:

* recall of every counted ground-truth object (the AP's objects: >= 25 px tall at KITTI's height, see
  :class:`~ablate.metrics.coco.MaskAP`) per condition group: found = a detection of its class, among all the
  detections AP sees, with mask IoU >= 0.5. For the RGB and DDM experts, their union (objects either expert finds:
  what a fusion could recover without learning anything new) and "RGB only" (found by RGB, missed by DDM: the
  room fusion has over the better expert), and for every fused row;
* the mean gate weight on each modality per condition group and fusion point (rows with a gated operator;
  SMoE eq. 2-3: W on f_i = RGB, 1 - W on f_j = DDM), averaged over channels and positions;
* the validation AP per epoch of each expert, from MLflow: whether an expert was still learning when it stopped;
* the experts' mask AP in clear weather, at night and in glare on the *same* test frames (each condition applied
  to all of them, so the columns differ by the condition only, not by which frames drew it), and the checks a
  dataset must pass before fused rows mean anything (:data:`CHECKS`): RGB in clear weather at least 0.6x DDM;
  objects found by RGB only and by DDM only each >= 10 %; the union >= 10 points above the better expert; night
  and glare lower the RGB expert's AP clearly (by >= 20 %) while the DDM expert's stays within 10 % of its
  clear-weather AP.

``experts_only=true`` evaluates the single-modal rows only: the data check, before any fused row is trained
(written to ``results/<table>_experts.md`` / ``.png``).

Writes ``results/<table>_diagnosis.md`` and ``.png``, and two figures of seed 0: ``<table>_masks.png`` (SMoE Fig.
6: ground truth and every row's masks on the busiest frame of each condition) and ``<table>_gates.png`` (the gate
maps of the table's last gated row on a night and a glare frame). Needs the table's checkpoints (``checkpoints/``,
kept by ``python -m ablate -m experiment=...``): a missing one is named with the command that makes it.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass, field
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
import torch  # noqa: E402
from hydra.utils import instantiate  # noqa: E402
from omegaconf import DictConfig  # noqa: E402
from tqdm import tqdm  # noqa: E402

from ablate import cli  # noqa: E402
from ablate.config import compose  # noqa: E402
from ablate.data.difficulty import counted  # noqa: E402
from ablate.jobs.experts import EXPERTS_TABLE, expert_config, load_model  # noqa: E402
from ablate.metrics.coco import MaskAP  # noqa: E402
from ablate.store import Tracker, config_hash, retry  # noqa: E402
from ablate.tasks.yolact.figures import draw_rows  # noqa: E402
from ablate.tasks.yolact.task import CONDITION_GROUPS, condition_group  # noqa: E402

IOU = 0.5


class MissingCheckpoint(FileNotFoundError):
    pass


def checkpoint(cfg: DictConfig, table: str, row: str = "?") -> Path:
    """The best checkpoint of a job: its expert's for a single-modal row of a two-stage table, else the job's own
    (looked up under every table, since a row shared by two tables is trained once)."""
    if cfg.stage.name == "single" and cfg.get("experts"):
        chash = config_hash(expert_config(cfg, cfg.stage.modality))
        found = [Path("checkpoints") / EXPERTS_TABLE / chash / "best.ckpt"]
    else:
        chash = config_hash(cfg)
        found = sorted(Path("checkpoints").glob(f"*/{chash}/best.ckpt"))
    found = [p for p in found if p.exists()]
    if not found:
        raise MissingCheckpoint(
            f"no checkpoint for row {row} seed {cfg.seed} (config {chash}) "
            f"under {Path('checkpoints').resolve()}: run `python -m ablate -m experiment={table}` "
            "with the same overrides first"
        )
    return found[0]


def found_objects(pred: dict, target: dict, height: int) -> tuple[np.ndarray, np.ndarray]:
    """(counted, found) per ground-truth object of one image: counted = tall enough for the AP; found = a
    same-class detection with mask IoU >= 0.5."""
    gt, labels = target["masks"].bool(), target["labels"]
    if "boxes" in target:
        tall = (target["boxes"][:, 3] - target["boxes"][:, 1]).cpu()
    else:  # the tight box of the mask, as MaskAP
        rows = gt.any(2)
        tall = torch.tensor([(r.nonzero().max() - r.nonzero().min() + 1).item() if r.any() else 0 for r in rows])
    is_counted = counted(tall.double(), height).numpy()
    found = np.zeros(len(gt), dtype=bool)
    if len(gt) and len(pred["masks"]):
        g = gt.flatten(1).float()
        p = pred["masks"].bool().flatten(1).float().to(g.device)
        inter = g @ p.T
        union = g.sum(1, keepdim=True) + p.sum(1) - inter
        iou = inter / union.clamp(min=1)
        same = labels.view(-1, 1).to(pred["labels"].device) == pred["labels"].view(1, -1)
        found = ((iou * same.to(iou.device)) >= IOU).any(1).cpu().numpy()
    return is_counted, found


@dataclass
class Evaluation:
    """One checkpoint on the test split: per counted GT object (image, object, group, found), per image x fusion
    point x modality the mean gate, the frame with the most objects of each condition group (image, target,
    prediction) and the first batch holding a night and a glare frame, or else the first batch (for the gate
    figure)."""

    objects: pd.DataFrame
    gates: pd.DataFrame
    showcase: dict = field(default_factory=dict)
    gate_batch: dict | None = None
    task: object = None


def evaluate(cfg: DictConfig, ckpt: Path, datamodule) -> Evaluation:
    model = load_model(cfg, ckpt).eval()
    task = instantiate(cfg.task, model=model)
    ops = [
        op for op in (model.fusion_modules() if hasattr(model, "fusion_modules") else []) if hasattr(op, "last_gates")
    ]
    names = list(model.modalities)
    objects, gates, image, showcase, gate_batch = [], [], 0, {}, None
    with torch.no_grad():
        for batch in datamodule.test_dataloader():
            inputs = {k: v for k, v in batch.items() if torch.is_tensor(v) and k in names}
            outputs = model(inputs)
            size = task.image_size(batch)
            preds = task.predict(outputs, size)
            conditions = batch.get("condition") or ["?"] * len(preds)
            if gate_batch is None or (
                not {"night", "glare"} <= set(gate_batch["condition"] or []) and {"night", "glare"} <= set(conditions)
            ):
                gate_batch = batch  # the first holding a night and a glare frame, else the first
            for b, (pred, target) in enumerate(zip(preds, task.targets(batch))):
                group = condition_group(conditions[b]) or conditions[b]
                is_counted, found = found_objects(pred, target, size[0])
                objects += [
                    {"image": image + b, "object": i, "group": group, "found": bool(f)}
                    for i, (c, f) in enumerate(zip(is_counted, found))
                    if c
                ]
                for level, op in enumerate(ops):
                    for m, gate in zip(names, op.last_gates or []):
                        gates.append(
                            {
                                "image": image + b,
                                "group": group,
                                "point": level,
                                "modality": m,
                                "gate": float(gate[b].float().mean()),
                            }
                        )
                if group not in showcase or len(target["labels"]) > len(showcase[group][1]["labels"]):
                    shown = batch["rgb"][b] if "rgb" in batch else inputs[names[0]][b]
                    showcase[group] = (shown, target, pred)  # the frame with the most objects of its group
            image += len(preds)
    return Evaluation(pd.DataFrame(objects), pd.DataFrame(gates), showcase, gate_batch, task)


def expert_curves(cfg: DictConfig, experts: dict[str, DictConfig]) -> pd.DataFrame:
    """Validation AP per epoch of each expert (seed, modality), from the MLflow experiment ``experts``."""
    tracker = Tracker.from_config(cfg)
    exp = retry(tracker.client.get_experiment_by_name, EXPERTS_TABLE)
    out = []
    for (seed, modality), ecfg in experts.items():
        runs = (
            []
            if exp is None
            else tracker.runs(
                exp.experiment_id, f"attributes.status = 'FINISHED' and tags.config_hash = '{config_hash(ecfg)}'"
            )
        )
        if runs:
            history = retry(tracker.client.get_metric_history, runs[0].info.run_id, "val/map")
            out += [{"seed": seed, "modality": modality, "step": h.step, "val_map": h.value} for h in history]
    return pd.DataFrame(out, columns=["seed", "modality", "step", "val_map"])


#: The conditions the data checks compare (each applied to the whole test split in turn).
CHECKED_CONDITIONS = ("clear", "night", "glare")


def ap_per_condition(cfg: DictConfig, ckpt: Path) -> dict[str, float]:
    """Mask AP (%) of a checkpoint on the whole test split under each of :data:`CHECKED_CONDITIONS` in turn."""
    model = load_model(cfg, ckpt).eval()
    task = instantiate(cfg.task, model=model)
    names = list(model.modalities)
    out = {}
    for condition in CHECKED_CONDITIONS:
        datamodule = instantiate(cfg.data, conditions=[condition])
        datamodule.setup("test")
        metric = MaskAP()
        with torch.no_grad():
            for batch in datamodule.test_dataloader():
                outputs = model({k: v for k, v in batch.items() if torch.is_tensor(v) and k in names})
                metric.update(task.predict(outputs, task.image_size(batch)), task.targets(batch))
        out[condition] = float(metric.compute()["map"]) * 100
    return out


def diagnose(overrides: list[str], experts_only: bool = False) -> dict:
    """Evaluate every row of the table (only its single-modal rows with ``experts_only``) for every seed; returns
    the per-object and gate frames, the experts' curves and their AP per condition."""
    base = compose(overrides)
    table = base.table
    if not base.get("experts"):
        raise ValueError(f"{table.name}: not a two-stage table (experts: null); nothing to compare fusion with")
    objects, gates, experts, showcase, gate_figure, conditions = [], [], {}, {}, None, []
    jobs = [(seed, spec) for seed in range(int(base.scale.seeds)) for spec in table.rows]
    for seed, spec in tqdm(jobs, desc=f"diagnose {table.name}", unit="job"):
        cfg = compose(overrides + [f"row={spec.row}", f"seed={seed}"])
        if cfg.stage.name == "single":
            experts[(seed, cfg.stage.modality)] = expert_config(cfg, cfg.stage.modality)
        elif experts_only:
            continue
        ckpt = checkpoint(cfg, table.name, spec.row)
        datamodule = instantiate(cfg.data)
        datamodule.prepare_data()
        datamodule.setup("test")
        ev = evaluate(cfg, ckpt, datamodule)
        if cfg.stage.name == "single":
            conditions += [
                {"seed": seed, "modality": cfg.stage.modality, "condition": c, "map": v}
                for c, v in ap_per_condition(cfg, ckpt).items()
            ]
        for frame, into in ((ev.objects, objects), (ev.gates, gates)):
            if len(frame):
                into.append(
                    frame.assign(
                        seed=seed, row=spec.row, name=spec.get("name", spec.row), modality_row=cfg.stage.get("modality")
                    )
                )
        if seed == 0:
            showcase[spec.get("name", spec.row)] = ev.showcase
            if len(ev.gates) and ev.gate_batch is not None:  # the last gated row of the table wins
                if gate_figure is not None:
                    plt.close(gate_figure)
                gate_figure = ev.task.gate_figure(ev.gate_batch)
    return {
        "table": table,
        "objects": pd.concat(objects, ignore_index=True) if objects else pd.DataFrame(),
        "gates": pd.concat(gates, ignore_index=True) if gates else pd.DataFrame(),
        "curves": expert_curves(base, experts),
        "showcase": showcase,
        "gate_figure": gate_figure,
        "conditions": pd.DataFrame(conditions, columns=["seed", "modality", "condition", "map"]),
        "experts_only": experts_only,
    }


def recall_table(objects: pd.DataFrame) -> pd.DataFrame:
    """Recall in percent per (row or expert union) x condition group, mean and std over seeds; rows in the
    order they first appear in ``objects`` (the table's)."""
    found = objects.pivot_table(
        index=["seed", "group", "image", "object"], columns="row", values="found", aggfunc="first"
    )[list(objects["row"].unique())]
    single = objects.drop_duplicates("row").set_index("row")["modality_row"].dropna().to_dict()
    by_modality = {m: r for r, m in single.items()}
    if {"rgb", "ddm_jet"} <= set(by_modality):
        rgb, ddm = found[by_modality["rgb"]].astype(bool), found[by_modality["ddm_jet"]].astype(bool)
        found["RGB ∪ DDM"] = rgb | ddm
        found["RGB only"] = rgb & ~ddm
        found["DDM only"] = ddm & ~rgb
    per = found.astype(float).groupby(level=["seed", "group"]).mean() * 100
    overall = found.astype(float).groupby(level="seed").mean() * 100
    overall["group"] = "all"
    per = pd.concat([per.reset_index(), overall.reset_index()], ignore_index=True).drop(columns="seed")
    counts = found.groupby(level=["seed", "group"]).size().groupby(level="group").mean()
    stats = per.groupby("group").agg(["mean", "std"])
    stats[("objects", "mean")] = counts.reindex(stats.index).fillna(found.groupby(level="seed").size().mean())
    order = [g for g in [*CONDITION_GROUPS, "all"] if g in stats.index]
    return stats.loc[order]


def gate_table(gates: pd.DataFrame) -> pd.DataFrame:
    """Mean gate weight on each modality per (row, fusion point) x condition group, mean over images and seeds."""
    if gates.empty:
        return gates
    g = gates.groupby(["name", "point", "modality", "group"])["gate"].mean().unstack("group")
    g["all"] = gates.groupby(["name", "point", "modality"])["gate"].mean()
    return g[[c for c in [*CONDITION_GROUPS, "all"] if c in g.columns]]


#: The data checks (issue: data where each sensor sees what the other misses): name -> threshold.
CHECKS = {
    "RGB AP in clear weather / DDM AP in clear weather": 0.6,
    "found by RGB only (%)": 10.0,
    "found by DDM only (%)": 10.0,
    "union minus the better expert (recall points)": 10.0,
    "RGB AP drop at night (%)": 20.0,
    "RGB AP drop in glare (%)": 20.0,
    "DDM AP change at night or in glare (%, at most)": 10.0,
}


def checks(result: dict) -> pd.DataFrame:
    """The :data:`CHECKS` on the experts: value (mean over seeds) and whether it passes."""
    ap = result["conditions"].groupby(["modality", "condition"])["map"].mean()
    rec = recall_table(result["objects"])
    single = result["objects"].drop_duplicates("row").set_index("row")["modality_row"].dropna()
    row = {m: r for r, m in single.items()}
    if ap.empty or not {"rgb", "ddm_jet"} <= set(row):
        return pd.DataFrame(columns=["check", "value", "threshold", "passes"])
    rgb, ddm = ap["rgb"], ap["ddm_jet"]
    overall = rec.loc["all"]
    values = [
        rgb["clear"] / ddm["clear"],
        overall[("RGB only", "mean")],
        overall[("DDM only", "mean")],
        overall[("RGB ∪ DDM", "mean")] - max(overall[(row["rgb"], "mean")], overall[(row["ddm_jet"], "mean")]),
        100 * (1 - rgb["night"] / rgb["clear"]),
        100 * (1 - rgb["glare"] / rgb["clear"]),
        100 * max(abs(ddm["night"] / ddm["clear"] - 1), abs(ddm["glare"] / ddm["clear"] - 1)),
    ]
    at_most = [name.endswith("at most)") for name in CHECKS]
    return pd.DataFrame(
        {
            "check": list(CHECKS),
            "value": values,
            "threshold": list(CHECKS.values()),
            "passes": [v <= t if m else v >= t for v, t, m in zip(values, CHECKS.values(), at_most)],
        }
    )


def conditions_markdown(result: dict) -> list[str]:
    """The experts' AP per condition on the same frames, and the data checks."""
    cond = result["conditions"]
    if cond.empty:
        return []
    stats = cond.groupby(["modality", "condition"])["map"].agg(["mean", "std"])
    order = list(dict.fromkeys(cond["condition"]))
    table = pd.DataFrame(
        {
            c: [
                f"{stats.loc[(m, c), 'mean']:.2f} ± {stats.loc[(m, c), 'std']:.2f}" if (m, c) in stats.index else ""
                for m in cond["modality"].unique()
            ]
            for c in order
        },
        index=cond["modality"].unique(),
    )
    chk = checks(result)
    chk["value"] = [f"{v:.2f}" for v in chk["value"]]
    chk["passes"] = ["yes" if p else "**no**" for p in chk["passes"]]
    return [
        "",
        "Experts' mask AP (%) on the whole test split under each condition (the same frames in every "
        f"column), mean ± std over {cond['seed'].nunique()} seed(s):",
        "",
        table.reset_index(names="expert").to_markdown(index=False, disable_numparse=True),
        "",
        "Checks of the data on the experts alone (means over seeds; drops are relative to clear weather):",
        "",
        chk.to_markdown(index=False, disable_numparse=True),
    ]


def to_markdown(result: dict) -> str:
    table, objects = result["table"], result["objects"]
    rec = recall_table(objects)
    names = objects.drop_duplicates("row").set_index("row")["name"].to_dict()
    cols = [c for c in rec.columns.get_level_values(0).unique() if c != "objects"]
    out = pd.DataFrame({"condition": rec.index, "objects / seed": [f"{v:.0f}" for v in rec[("objects", "mean")]]})
    for c in cols:
        mean, std = rec[(c, "mean")], rec[(c, "std")]
        out[names.get(c, c)] = [f"{m:.1f}" + ("" if np.isnan(s) else f" ± {s:.1f}") for m, s in zip(mean, std)]
    seeds = objects["seed"].nunique()
    heading = "Data check on the experts of" if result.get("experts_only") else "Diagnosis of"
    lines = [
        f"# {heading} {table.title}",
        "",
        f"Recall (%) of the counted test objects (mask IoU >= {IOU} with a detection of their class, among all "
        f"detections the AP sees), mean ± std over {seeds} seed(s). *RGB ∪ DDM*: found by either expert; "
        "*RGB only*: found by the RGB expert and missed by the DDM expert, the most a fusion of the two "
        "experts could add to the DDM expert's recall without learning anything new.",
        "",
        out.to_markdown(index=False, disable_numparse=True),
    ] + conditions_markdown(result)
    gates = result["gates"]
    if len(gates) and "rgb" in set(gates["modality"]):
        gates = gates[gates["modality"] == "rgb"]
    gates = gate_table(gates)
    if len(gates):
        g = gates.reset_index()
        g["point"] = [
            f"P{3 + p}" if len(gates.index.get_level_values("point").unique()) == 5 else str(p) for p in g["point"]
        ]
        g = g.rename(columns={"name": "row", "point": "fusion point"})
        lines += [
            "",
            "Mean gate weight on RGB (channels, positions, images and seeds averaged; the MoE operators "
            "weight DDM by 1 minus it), per fusion point and condition.",
            "",
            g.to_markdown(index=False, floatfmt=".3f"),
        ]
    curves = result["curves"]
    if len(curves):
        last = (
            curves.sort_values("step")
            .groupby(["modality", "seed"])
            .agg(
                first=("val_map", "first"),
                best=("val_map", "max"),
                last=("val_map", "last"),
                epochs=("val_map", "size"),
            )
        )
        lines += [
            "",
            "Experts' validation mask AP (%) over their epochs (first, best, last):",
            "",
            last.reset_index().to_markdown(index=False, floatfmt=".2f"),
        ]
    lines += [
        "",
        "Regenerated by `python -m ablate.diagnose` from the checkpoints and MLflow runs; do not edit by hand.",
        "",
    ]
    return "\n".join(lines)


def plot(result: dict):
    """Recall per condition (experts, their union, fused rows); gates on RGB per condition; experts' val AP."""
    objects, gates, curves = result["objects"], result["gates"], result["curves"]
    rec = recall_table(objects)
    names = objects.drop_duplicates("row").set_index("row")["name"].to_dict()
    cols = [c for c in rec.columns.get_level_values(0).unique() if c not in ("objects", "RGB only", "DDM only")]
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.6), gridspec_kw={"width_ratios": [2.2, 1, 1]})
    x, width = np.arange(len(rec)), 0.8 / max(len(cols), 1)
    for k, c in enumerate(cols):
        axes[0].bar(
            x + (k - (len(cols) - 1) / 2) * width,
            rec[(c, "mean")],
            width,
            yerr=rec[(c, "std")].fillna(0),
            capsize=2,
            label=names.get(c, c),
        )
    axes[0].set_xticks(x, rec.index)
    axes[0].set_ylabel(f"recall % (mask IoU >= {IOU})")
    axes[0].legend(fontsize=7, ncol=4, loc="upper center", bbox_to_anchor=(0.5, -0.1))
    axes[0].set_title("Objects found, per condition", fontsize=9)
    if len(gates) and "rgb" in set(gates["modality"]):
        order = [spec.row for spec in result["table"].rows]
        last = max(gates["row"].unique(), key=lambda r: order.index(r) if r in order else -1)
        rgb = gate_table(gates[(gates["row"] == last) & (gates["modality"] == "rgb")])
        points = rgb.index.get_level_values("point")
        for (_name, point, _), values in rgb.iterrows():
            label = f"P{3 + point}" if points.nunique() == 5 else f"point {point}"
            axes[1].plot(values.index, values.values, marker="o", label=label)
        axes[1].axhline(0.5, color="grey", lw=0.8, ls="--")
        axes[1].set_ylabel("mean gate on RGB")
        axes[1].legend(fontsize=6)
        axes[1].set_title(f"Gate on RGB: {names.get(last, last)}", fontsize=9)
    for (modality, seed), c in curves.groupby(["modality", "seed"]):
        axes[2].plot(
            np.arange(1, len(c) + 1),
            c.sort_values("step")["val_map"],
            marker=".",
            color="C0" if modality == "rgb" else "C1",
            label=f"{modality} seed {seed}",
        )
    axes[2].set_xlabel("epoch")
    axes[2].set_ylabel("val mask AP %")
    axes[2].legend(fontsize=6)
    axes[2].set_title("Experts while training", fontsize=9)
    fig.suptitle(f"Diagnosis: {result['table'].title}", fontsize=10)
    fig.tight_layout()
    return fig


def masks_figure(showcase: dict[str, dict]):
    """SMoE Fig. 6: the test frame with the most objects of each condition group, ground truth and every row's
    masks (seed 0)."""
    first = next(iter(showcase.values()))
    groups = [g for g in CONDITION_GROUPS if g in first] + [g for g in first if g not in CONDITION_GROUPS]
    images = torch.stack([first[g][0] for g in groups])
    targets = [first[g][1] for g in groups]
    preds = {name: [frames[g][2] for g in groups] for name, frames in showcase.items()}
    return draw_rows(images, targets, preds, groups)


def main(argv: list[str] | None = None) -> int:
    """``python -m ablate.diagnose [experiment=<table>] [experts_only=true] [key=value ...]``, its arguments read by
    :func:`ablate.cli.diagnose` (``--help`` and a bad option end the process there, status 0 and 2): write the
    diagnosis and its figures; 1 where the table cannot be diagnosed here (a missing checkpoint)."""
    parsed = cli.diagnose(__doc__, argv)
    experts_only = parsed.experts_only
    try:
        result = diagnose(parsed.overrides, experts_only)
    except (MissingCheckpoint, ValueError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 1
    out = Path("results")
    out.mkdir(exist_ok=True)
    stem = out / f"{result['table'].name}_{'experts' if experts_only else 'diagnosis'}"
    md, png = stem.with_suffix(".md"), stem.with_suffix(".png")
    md.write_text(to_markdown(result))
    figures = {png: plot(result)}
    if not experts_only:
        figures[out / f"{result['table'].name}_masks.png"] = masks_figure(result["showcase"])
    if result["gate_figure"] is not None:
        figures[out / f"{result['table'].name}_gates.png"] = result["gate_figure"]
    print(md)
    for path, fig in figures.items():
        fig.savefig(path, dpi=100, metadata={"Software": None})
        plt.close(fig)
        print(path)
    return 0
