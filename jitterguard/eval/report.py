"""Files of an evaluation run: metrics.json, report.md and the figures (the only I/O of the eval package).

Figures: speed vs z per group coloured by ground-truth state (the paper's Fig. 5, where the jitter band shows
as static points with non-zero speed and moderate z), precision–recall curves of both scores, and the
false-/missed-dynamic rates as alpha sweeps.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from .metrics import alpha_sweep, pr_curve, scored_rows
from .pipeline import Records

PLOT_GROUPS = ("vehicle", "pedestrian", "bicycle")


def _plt():  # type: ignore[no-untyped-def]
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_speed_vs_z(rec: Records, path: Path) -> None:
    """Per group: tracker speed against z (log), static and dynamic GT in two colours, both cut-offs drawn."""
    plt = _plt()
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.5))
    for ax, g in zip(axes, PLOT_GROUPS):
        m = scored_rows(rec, g)
        z = np.clip(rec.z[m], 1e-2, 1e3)
        for dyn, colour, name in ((False, "tab:blue", "static (GT)"), (True, "tab:red", "dynamic (GT)")):
            k = rec.gt_dynamic[m] == dyn
            ax.scatter(z[k], rec.speed[m][k], s=4, alpha=0.35, c=colour, label=f"{name} n={int(k.sum())}",
                       edgecolors="none")
        alpha = float(np.median(rec.alpha[m])) if m.any() else 1.96
        ax.axvline(alpha, ls="--", c="k", lw=1, label=f"alpha {alpha:g}")
        ax.axhline(rec.velocity_threshold, ls=":", c="k", lw=1, label=f"{rec.velocity_threshold:g} m/s")
        ax.set_xscale("log")
        ax.set_xlim(1e-2, 1e3)  # one z range in every panel, so groups and runs compare at a glance
        ax.set_xlabel("z = max(z_x, z_y)")
        ax.set_ylabel("tracker speed [m/s]")
        ax.set_title(g)
        ax.legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def plot_pr(rec: Records, path: Path) -> None:
    """Precision–recall of "dynamic" per group, z and speed as scores."""
    plt = _plt()
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.2))
    for ax, g in zip(axes, PLOT_GROUPS):
        m = scored_rows(rec, g)
        dyn = rec.gt_dynamic[m]
        if dyn.any():
            for score, name in ((rec.z[m], "z-test"), (rec.speed[m], "speed")):
                p, r, _ = pr_curve(score, dyn)
                ax.plot(np.r_[0.0, r], np.r_[1.0, p], label=name)
        ax.set_xlim(0, 1.01)
        ax.set_ylim(0, 1.01)
        ax.set_xlabel("recall (dynamic)")
        ax.set_ylabel("precision")
        ax.set_title(g)
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


ALPHAS = np.round(np.linspace(0.25, 8.0, 32), 3)


def plot_alpha_sweep(rec: Records, path: Path) -> dict[str, Any]:
    """False-/missed-dynamic rate against alpha per group; returns the sweep for metrics.json."""
    plt = _plt()
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.2))
    sweeps = {}
    for ax, g in zip(axes, PLOT_GROUPS):
        sw = alpha_sweep(rec, g, ALPHAS)
        sweeps[g] = sw
        ax.plot(sw["alpha"], sw["false_dynamic"], label="false dynamic (static GT)")
        ax.plot(sw["alpha"], sw["missed_dynamic"], label="missed dynamic (moving GT)")
        ax.axvline(1.96, ls="--", c="grey", lw=1)
        ax.set_xlabel("alpha")
        ax.set_ylabel("rate")
        ax.set_ylim(0, 1.01)
        ax.set_title(g)
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return sweeps


def finite_json(obj: Any) -> Any:
    """``obj`` with every NaN / inf float replaced by None: metrics.json must be strict JSON (an undefined
    AP — no dynamic object in a group — is null, not a non-standard NaN token)."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: finite_json(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [finite_json(v) for v in obj]
    return obj


def _fmt(v: Any) -> str:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "—"
    return f"{v:.3f}" if isinstance(v, float) else str(v)


def write_outputs(out: Path, rec: Records, metrics: dict[str, Any]) -> dict[str, Any]:
    """Write figures, metrics.json (with the alpha sweep added) and report.md into ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    plot_speed_vs_z(rec, out / "speed_vs_z.png")
    plot_pr(rec, out / "pr_curves.png")
    metrics["alpha_sweep"] = plot_alpha_sweep(rec, out / "alpha_sweep.png")
    metrics = finite_json(metrics)
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2, sort_keys=True, allow_nan=False) + "\n")
    run = metrics["run"]
    lines = [
        f"# jitterguard eval — {run['source']}",
        "",
        f"Input `{run['input']}`, noise `{run['noise']}`, seed {run['seed']}, {run['frames']} frames, "
        f"{run['rows']} (frame, track) rows, {run['matched_rows']} matched to ground truth "
        f"(≤ {run['match_distance_m']} m). Operating points: z-test alpha {run['alpha']}, "
        f"velocity threshold {run['velocity_threshold']} m/s. Scored rows: matched, z-test window ≥ "
        f"{run['min_window']}.",
        "",
        "| group | n static | n dynamic | AP z | AP speed | false dyn z | false dyn speed | missed dyn z "
        "| missed dyn speed | first correct z [s] | first correct speed [s] |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for g, m in metrics["motion"].items():
        lines.append(
            f"| {g} | {m['n_static']} | {m['n_dynamic']} | {_fmt(m['ap_z'])} | {_fmt(m['ap_speed'])} | "
            f"{_fmt(m['false_dynamic_z'])} | {_fmt(m['false_dynamic_speed'])} | {_fmt(m['missed_dynamic_z'])} | "
            f"{_fmt(m['missed_dynamic_speed'])} | {_fmt(m['time_to_first_correct_s_median_z'])} | "
            f"{_fmt(m['time_to_first_correct_s_median_speed'])} |")
    if metrics.get("alpha_from_labels"):
        lines += ["", "Alpha from labels (missed dynamic ≤ 5 %): "
                  + ", ".join(f"{g} {_fmt(a)}" for g, a in metrics["alpha_from_labels"].items())]
    lines += ["", "![speed vs z](speed_vs_z.png)", "", "![PR curves](pr_curves.png)", "",
              "![alpha sweep](alpha_sweep.png)", ""]
    (out / "report.md").write_text("\n".join(lines))
    return metrics
