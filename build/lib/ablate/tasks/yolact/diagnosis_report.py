"""The tables and figures of SMoE's diagnosis (:mod:`ablate.tasks.yolact.diagnose`): recall per condition group
of every row and of the experts' union, the gates per condition, the data checks a dataset must pass before fused
rows mean anything (:data:`CHECKS`), the experts' AP per condition, and SMoE Fig. 6 (every row's masks on the
busiest frame of each condition)."""

from __future__ import annotations

from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
import torch  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402

from ablate.tasks.yolact.diagnose import IOU  # noqa: E402
from ablate.tasks.yolact.figures import draw_rows  # noqa: E402
from ablate.tasks.yolact.task import CONDITION_GROUPS  # noqa: E402


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


def to_markdown(result: dict[str, Any]) -> str:
    """The diagnosis as markdown: recall per condition, the experts' AP per condition and the data checks, the
    gates on RGB, and the experts' validation AP over their epochs."""
    table, objects = result["table"], result["objects"]
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
        recall_markdown(objects),
    ] + conditions_markdown(result)
    lines += gates_markdown(result["gates"]) + curves_markdown(result["curves"])
    lines += [
        "",
        "Regenerated by `python -m ablate.diagnose` from the checkpoints and MLflow runs; do not edit by hand.",
        "",
    ]
    return "\n".join(lines)


def recall_markdown(objects: pd.DataFrame) -> str:
    """Recall per condition group of every row and of the experts' union, mean ± std over seeds."""
    rec = recall_table(objects)
    names = objects.drop_duplicates("row").set_index("row")["name"].to_dict()
    cols = [c for c in rec.columns.get_level_values(0).unique() if c != "objects"]
    out = pd.DataFrame({"condition": rec.index, "objects / seed": [f"{v:.0f}" for v in rec[("objects", "mean")]]})
    for c in cols:
        mean, std = rec[(c, "mean")], rec[(c, "std")]
        out[names.get(c, c)] = [f"{m:.1f}" + ("" if np.isnan(s) else f" ± {s:.1f}") for m, s in zip(mean, std)]
    return str(out.to_markdown(index=False, disable_numparse=True))


def gates_markdown(gates: pd.DataFrame) -> list[str]:
    """The mean gate on RGB per fusion point and condition (no lines for a table without gated rows)."""
    if len(gates) and "rgb" in set(gates["modality"]):
        gates = gates[gates["modality"] == "rgb"]
    gates = gate_table(gates)
    if not len(gates):
        return []
    g = gates.reset_index()
    g["point"] = [
        f"P{3 + p}" if len(gates.index.get_level_values("point").unique()) == 5 else str(p) for p in g["point"]
    ]
    g = g.rename(columns={"name": "row", "point": "fusion point"})
    return [
        "",
        "Mean gate weight on RGB (channels, positions, images and seeds averaged; the MoE operators "
        "weight DDM by 1 minus it), per fusion point and condition.",
        "",
        g.to_markdown(index=False, floatfmt=".3f"),
    ]


def curves_markdown(curves: pd.DataFrame) -> list[str]:
    """Each expert's validation AP over its epochs: first, best, last (no lines without curves)."""
    if not len(curves):
        return []
    last = (
        curves.sort_values("step")
        .groupby(["modality", "seed"])
        .agg(first=("val_map", "first"), best=("val_map", "max"), last=("val_map", "last"), epochs=("val_map", "size"))
    )
    return [
        "",
        "Experts' validation mask AP (%) over their epochs (first, best, last):",
        "",
        last.reset_index().to_markdown(index=False, floatfmt=".2f"),
    ]


def plot(result: dict[str, Any]) -> Figure:
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


def masks_figure(showcase: dict[str, dict[str, Any]]) -> Figure:
    """SMoE Fig. 6: the test frame with the most objects of each condition group, ground truth and every row's
    masks (seed 0)."""
    first = next(iter(showcase.values()))
    groups = [g for g in CONDITION_GROUPS if g in first] + [g for g in first if g not in CONDITION_GROUPS]
    images = torch.stack([first[g][0] for g in groups])
    targets = [first[g][1] for g in groups]
    preds = {name: [frames[g][2] for g in groups] for name, frames in showcase.items()}
    return draw_rows(images, targets, preds, groups)
