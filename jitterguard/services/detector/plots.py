"""Figures of the detector evaluation (the only I/O next to :mod:`.evaluate`): the positional calibration plot
(the paper's Fig. 3) and per-class precision–recall curves. matplotlib with the Agg backend, no display."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from ...files import save_figure
from .evaluate import AXES, COUNT_THRESHOLD_M, MIN_PRECISION, MIN_RECALL, threshold_key


def _plt():  # type: ignore[no-untyped-def]
    import matplotlib  # only when a plot is written (start-up time); the Agg backend is chosen first

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def calibration_plot(result: dict[str, Any], path: str | Path, *, title: str = "") -> None:
    """Observed SD (RMS residual) against predicted SD per σ bin, one panel per axis, with the diagonal of
    perfect calibration and the bin counts as bars underneath (the paper's Fig. 3). ``result`` is
    :func:`.evaluate.calibration`'s dict (or its JSON round trip)."""
    plt = _plt()
    fig, axes = plt.subplots(1, 2, figsize=(10, 4.6))
    for ax, name in zip(axes, AXES):
        a = result["axes"][name]
        b = a["bins"]
        pred = np.asarray(b["pred_sd"], dtype=float)
        obs = np.asarray(b["obs_sd"], dtype=float)
        lo = np.asarray(b["sigma_lo"], dtype=float)
        hi = np.asarray(b["sigma_hi"], dtype=float)
        top = float(max(pred.max(initial=0.0), obs.max(initial=0.0), hi.max(initial=0.0), 1e-3)) * 1.05
        counts_ax = ax.twinx()
        # one bar per bin, spanning its σ range: equal-count bins show as equal heights of varying width
        counts_ax.bar((lo + hi) / 2, b["count"], width=np.maximum(hi - lo, top / 200), color="0.85",
                      edgecolor="white", linewidth=1.0, zorder=0)
        counts_ax.set_ylabel("matches per bin", color="0.45")
        counts_ax.set_ylim(0, max(b["count"], default=1) * 4)  # bars stay in the lower quarter
        ax.set_zorder(counts_ax.get_zorder() + 1)
        ax.patch.set_visible(False)
        ax.plot([0, top], [0, top], "k--", lw=1, label="calibrated")
        ax.plot(pred, obs, "o-", c="tab:blue", label="observed")
        ece = a.get("ece")
        ax.set_title(f"{name}: ECE {ece:.3f} m" if isinstance(ece, float) else f"{name}: no matches")
        ax.set_xlim(0, top)
        ax.set_ylim(0, top)
        ax.set_xlabel(f"predicted SD σ_{name} [m]")
        ax.set_ylabel(f"observed SD of the {name} error [m]")
        ax.legend(loc="upper left", fontsize=8)
    ece_all = result.get("ece")
    default = f"positional calibration: {result.get('num_matched', 0)} true positives" + (
        f", positional ECE {ece_all:.3f} m" if isinstance(ece_all, float) else "")
    fig.suptitle(title or default)
    fig.tight_layout()
    save_figure(fig, path, dpi=90)
    plt.close(fig)


def pr_plot(ap_result: dict[str, Any], path: str | Path, *, threshold: float = COUNT_THRESHOLD_M) -> None:
    """Interpolated precision against recall per class at one distance threshold (2 m by default), with the
    min-recall / min-precision lines below which nuScenes' AP gives no credit. ``ap_result`` is
    :func:`.evaluate.detection_ap`'s dict (with its curves)."""
    plt = _plt()
    key = threshold_key(threshold)
    # the curves are one threshold's, the mean APs (mAP, each class's AP in the JSON and report.md) every
    # threshold's: both are named (the legend had given the 2 m AP under a title with the mean mAP, and report.md's
    # AP column another number for the same class)
    thresholds = "/".join(threshold_key(t) for t in ap_result.get("thresholds_m", ())) + " m"
    recall = np.asarray(ap_result["recall"], dtype=float)
    fig, ax = plt.subplots(figsize=(6.4, 4.8))
    for name, c in ap_result["classes"].items():
        if not c["num_gt"]:
            continue
        mean = c.get("mean_ap")  # the AP the JSON and report.md give: the mean over the distance thresholds
        ax.plot(recall, c["precision"][key], label=f"{name}: AP {c['ap'][key]:.3f} at {key} m"
                + (f", {mean:.3f} over {thresholds}" if isinstance(mean, float) and math.isfinite(mean) else "")
                + f" (n={c['num_gt']})")
    ax.axvline(MIN_RECALL, ls=":", c="0.5", lw=1)
    ax.axhline(MIN_PRECISION, ls=":", c="0.5", lw=1)
    ax.set_xlim(0, 1.01)
    ax.set_ylim(0, 1.01)
    ax.set_xlabel("recall")
    ax.set_ylabel("precision")
    ax.set_title(f"precision–recall at {key} m (mAP {ap_result['mAP']:.3f} over {thresholds})"
                 if isinstance(ap_result.get("mAP"), float) and math.isfinite(ap_result["mAP"])
                 else f"precision–recall at {key} m")
    ax.legend(fontsize=8, loc="lower left")
    fig.tight_layout()
    save_figure(fig, path, dpi=90)
    plt.close(fig)
