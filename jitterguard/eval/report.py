"""Files of an evaluation run: metrics.json, report.md and the figures (the only I/O of the eval package).

Figures: speed vs z per group coloured by ground-truth state (the paper's Fig. 5, where the jitter band shows
as static points with non-zero speed and moderate z) with the tracks matched to no object (ghosts) as a third
colour, precision–recall curves of both scores, the false-/missed-dynamic rates as alpha sweeps, and the
variance calibration the classifier ended with (scales per group, line-of-sight axis, range band and track
age). With the detector in the loop also its positional calibration (the paper's Fig. 3) and per-class
detection precision–recall, drawn by the detector's own plotting code. Every scored row is drawn: z is clipped
into the axis range, not dropped.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from ..files import save_figure, write_atomically
from .metrics import alpha_sweep, average_precision, ghost_rows, pr_curve, scored_rows
from .pipeline import NOTHING_LABELLED, Records

PLOT_GROUPS = ("vehicle", "pedestrian", "bicycle")


def _plt():  # type: ignore[no-untyped-def]
    import matplotlib  # only when a plot is written (start-up time); the Agg backend is chosen first

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _panels(rec: Records, height: float, *, with_ghosts: bool = False) -> tuple[Any, Any, list[str]]:
    """A figure with one panel per group that has scored rows (or, ``with_ghosts``, ghost rows: a scene without
    cyclists gets no empty bicycle panel); one panel saying so when no group has any."""
    plt = _plt()
    groups = [g for g in PLOT_GROUPS if scored_rows(rec, g).any() or (with_ghosts and ghost_rows(rec, g).any())]
    fig, axes = plt.subplots(1, max(1, len(groups)), figsize=(5 * max(1, len(groups)), height), squeeze=False)
    if not groups:
        axes[0][0].text(0.5, 0.5, "no scored rows", ha="center", va="center", transform=axes[0][0].transAxes)
        axes[0][0].set_axis_off()
    return plt, fig, list(zip(axes[0], groups))


SCORE_AXIS = {"z_test": "z = max(z_x, z_y)", "chi2": "z of the χ² test (normal score of its p)"}
"""What the records' ``z`` is, per scored test (``run.mode``): in chi2 mode it is the χ² statistic's p-value as a
two-sided normal score (:func:`~.pipeline.chi2_as_z`), not the max of the axes' z."""
TEST_NAME = {"z_test": "z-test", "chi2": "χ² test"}


def plot_speed_vs_z(rec: Records, path: Path, mode: str = "z_test") -> None:
    """Per group: tracker speed against z (log), static and dynamic GT and ghost tracks in three colours, both
    cut-offs drawn (the median over the group's classes where they differ); ``mode`` (``run.mode``) names the
    score on the axis."""
    plt, fig, panels = _panels(rec, 4.5, with_ghosts=True)
    for ax, g in panels:
        m = scored_rows(rec, g)
        gh = ghost_rows(rec, g)
        for mask, colour, name in ((m & ~rec.gt_dynamic, "tab:blue", "static (GT)"),
                                   (m & rec.gt_dynamic, "tab:red", "dynamic (GT)"),
                                   (gh, "tab:gray", "ghost (no object)")):
            z = np.clip(rec.z[mask], 1e-2, 1e3)
            ax.scatter(z, rec.speed[mask], s=4, alpha=0.35, c=colour, label=f"{name} n={int(mask.sum())}",
                       edgecolors="none")
        both = m | gh
        alpha = float(np.median(rec.alpha[both])) if both.any() else 1.96
        thr = float(np.median(rec.speed_threshold[both])) if both.any() else rec.velocity_threshold
        ax.axvline(alpha, ls="--", c="k", lw=1, label=f"alpha {alpha:g}")
        ax.axhline(thr, ls=":", c="k", lw=1, label=f"{thr:g} m/s")
        ax.set_xscale("log")
        ax.set_xlim(1e-2, 1e3)  # one z range in every panel, so groups and runs compare at a glance
        ax.set_xlabel(SCORE_AXIS[mode])
        ax.set_ylabel("tracker speed [m/s]")
        ax.set_title(g)
        ax.legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    save_figure(fig, path, dpi=90)
    plt.close(fig)


def plot_pr(rec: Records, path: Path, mode: str = "z_test") -> None:
    """Precision–recall of "dynamic" per group, z and speed as scores.

    The z-test is drawn thick and solid, the speed rule thin and dashed on top of it, each with its AP in the
    legend: where the curves coincide (both perfect on an easy scene) the dashes show over the solid line."""
    plt, fig, panels = _panels(rec, 4.2)
    styles = ((TEST_NAME[mode], rec.z, dict(lw=3.0, ls="-", c="tab:blue", zorder=2)),
              ("speed", rec.speed, dict(lw=1.4, ls=(0, (4, 3)), c="tab:orange", zorder=3)))
    for ax, g in panels:
        m = scored_rows(rec, g)
        dyn = rec.gt_dynamic[m]
        if dyn.any() and not dyn.all():
            for name, score, style in styles:
                p, r, _ = pr_curve(score[m], dyn)
                ax.plot(np.r_[0.0, r], np.r_[1.0, p], label=f"{name} (AP {average_precision(score[m], dyn):.3f})",
                        **style)
            ax.legend(fontsize=8, loc="lower left")
        else:
            what = "no dynamic ground truth" if not dyn.any() else "no static ground truth"
            ax.text(0.5, 0.5, what, ha="center", va="center", transform=ax.transAxes)
        ax.set_xlim(0, 1.01)
        ax.set_ylim(0, 1.01)
        ax.set_xlabel("recall (dynamic)")
        ax.set_ylabel("precision")
        ax.set_title(g)
    fig.tight_layout()
    save_figure(fig, path, dpi=90)
    plt.close(fig)


ALPHAS = np.round(np.linspace(0.25, 8.0, 32), 3)


def plot_alpha_sweep(rec: Records, path: Path) -> dict[str, Any]:
    """False-/missed-dynamic rate against alpha per group; returns the sweep for metrics.json (every group)."""
    sweeps = {g: alpha_sweep(rec, g, ALPHAS) for g in PLOT_GROUPS}
    plt, fig, panels = _panels(rec, 4.2)
    for ax, g in panels:
        sw = sweeps[g]
        ax.plot(sw["alpha"], sw["false_dynamic"], label="false dynamic (static GT)")
        ax.plot(sw["alpha"], sw["missed_dynamic"], label="missed dynamic (moving GT)")
        m = scored_rows(rec, g)
        deployed = float(np.median(rec.alpha[m])) if m.any() else 1.96  # the run's alpha, not always 1.96
        ax.axvline(deployed, ls="--", c="grey", lw=1, label=f"alpha in force {deployed:g}")
        ax.set_xlabel("alpha")
        ax.set_ylabel("rate")
        ax.set_ylim(0, 1.01)
        ax.set_title(g)
        ax.legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, path, dpi=90)
    plt.close(fig)
    return sweeps


def plot_calibration(cal: dict[str, Any] | None, path: Path) -> bool:
    """The variance scales the online calibration ended with (log scale; 1 = the detector's variances as they
    are), per group and line-of-sight axis (along / across), one bar per range band in metres, established and
    young tracks side by side, with the blocks behind each. Returns False (nothing written) without a calibration."""
    if not cal:
        return False
    plt = _plt()
    groups = list(cal["groups"])
    fig, axes = plt.subplots(1, len(groups), figsize=(4 * len(groups), 4.2), sharey=True)
    for ax, g in zip(np.atleast_1d(axes), groups):
        entry = cal["groups"][g]
        labels, vals, colours, blocks = [], [], [], []
        for axis, colour in (("along", "tab:orange"), ("across", "tab:green")):
            a = entry[axis]
            for key, shade in (("scale", 1.0), ("scale_young", 0.45)):
                for band, v in a[key].items():
                    labels.append(f"{axis} {band} m{' young' if key == 'scale_young' else ''}")
                    vals.append(v)
                    colours.append((*plt.matplotlib.colors.to_rgb(colour), shade))
                    blocks.append(a["blocks" if key == "scale" else "blocks_young"][band])
        x = np.arange(len(vals))
        ax.bar(x, vals, color=colours)
        for xi, v, b in zip(x, vals, blocks):
            ax.text(xi, v, f"{b:.0f}", ha="center", va="bottom", fontsize=6)
        ax.axhline(1.0, c="k", lw=0.8)
        ax.set_yscale("log")
        ax.set_xticks(x)
        ax.set_xticklabels(labels, rotation=90, fontsize=6)
        ax.set_title(f"{g}: m {entry['along']['correlation']:.2f}/{entry['across']['correlation']:.2f}, "
                     f"ν₀ {entry['track_dof']:.0f}", fontsize=8)
    every = [v for g in groups for axis in ("along", "across") for key in ("scale", "scale_young")
             for v in cal["groups"][g][axis][key].values()]
    # room above the tallest bar for its block count and below the shortest, 1 always in view: with every scale
    # at 1 (a run too short to learn any) the axis had collapsed onto 1 and the counts ran into the titles
    np.atleast_1d(axes)[0].set_ylim(min(*every, 1.0) / 1.6, max(*every, 1.0) * 1.6)
    np.atleast_1d(axes)[0].set_ylabel("true / reported variance (blocks on top)")
    fig.tight_layout()
    save_figure(fig, path, dpi=90)
    plt.close(fig)
    return True


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


DETECTION_FIGURES = ("detection_calibration.png", "detection_pr.png")
FIGURES = ("speed_vs_z.png", "pr_curves.png", "alpha_sweep.png", "calibration.png", *DETECTION_FIGURES)
"""Every figure ``write_outputs`` may draw into its folder."""
OUTPUTS = ("metrics.json", "report.md")
"""The files ``write_outputs`` writes into its folder besides the figures."""


def plot_detection(report: dict[str, Any], out: Path) -> list[str]:
    """The detector's calibration plot (only for a model with variance heads) and its PR curves at 2 m;
    returns the file names written. ``report`` is :func:`~jitterguard.services.detector.evaluate.
    evaluation_report` with curves."""
    from ..services.detector.plots import calibration_plot, pr_plot

    written = []
    if report.get("calibration") is not None:
        calibration_plot(report["calibration"], out / DETECTION_FIGURES[0])
        written.append(DETECTION_FIGURES[0])
    pr_plot(report["detection"], out / DETECTION_FIGURES[1])
    written.append(DETECTION_FIGURES[1])
    return written


def detection_lines(det: dict[str, Any], figures: list[str]) -> list[str]:
    """report.md's detection section: mAP, positional ECE and per-class AP / counts."""
    lines = ["", "## Detector", "",
             f"nuScenes mAP {_fmt(det['map'])} over {det['num_samples']} scans (classes with ground truth); "
             f"positional ECE {_fmt(det['ece_pos'])} m (x {_fmt(det['ece_x'])}, y {_fmt(det['ece_y'])}; "
             f"{det['num_matched'] if det['num_matched'] is not None else '—'} true positives at 2 m), "
             f"coverage of ±1σ {_fmt(det['coverage_1sigma'])} (calibrated: 0.683).",
             "", "| class | AP | n GT | n pred | TP | FP | FN |", "|---|---|---|---|---|---|---|"]
    for name, c in det.items():
        if isinstance(c, dict) and "ap" in c:
            lines.append(f"| {name} | {_fmt(c['ap'])} | {c['num_gt']} | {c['num_pred']} | {c['tp']} | {c['fp']} | "
                         f"{c['fn']} |")
    for f in figures:
        lines += ["", f"![{f[:-4].replace('_', ' ')}]({f})"]
    return lines


def _latency(m: dict[str, Any], time: str, never: str, rule: str) -> str:
    """A median time to a decision and, beside it, the share of pairs that never reached one (``never_*``): the
    median is over the pairs that did, so alone it read 0.2 s where 4 of 5 moving pedestrians were never called
    dynamic."""
    t, n = m.get(f"time_to_{time}_s_median_{rule}"), m.get(f"never_{never}_fraction_{rule}")
    return _fmt(t) + (f" ({100 * n:.0f} % never)" if n and 100 * n >= 0.5 else " (< 1 % never)" if n else "")


def _vetoed_desc(vetoed: dict[str, dict[str, int]]) -> str:
    """``run.vetoed_rows`` in words: the scored rows the jump veto turned static, per group."""
    parts = [f"{g} {c['static']} static / {c['moving']} moving / {c['ghost']} ghost" for g, c in vetoed.items()
             if any(c.values())]
    return "rows it turned static: " + ("; ".join(parts) if parts else "none")


def _input_desc(run: dict[str, Any]) -> str:
    det = run.get("detector")
    if det is None:
        return f"noise `{run['noise']}`"
    w = "random initialisation (meaningless detections)" if det.get("random_init") else f"`{det['weights']}`"
    seen = [why for key, why in (("weights_trained_on_this_dataroot", "**trained on this dataroot's labels**"),
                                 ("weights_adapted_on_its_scans", "**adapted on its unlabelled scans**"))
            if det.get(key)]
    return f"detector weights {w}, preset `{det['preset']}`" + (
        f" ({' and '.join(seen)}: not an unseen scene)" if seen else "")


def _ci(m: dict[str, Any], key: str) -> str:
    ci = (m.get("ci90") or {}).get(key)
    return f"{_fmt(m.get(key))}" + (f" [{ci[0]:.3f}, {ci[1]:.3f}]" if ci else "")


def planner_lines(metrics: dict[str, Any]) -> list[str]:
    """report.md's sections on what a planner sees: ghosts, matched operating points, attributes, full windows."""
    lines = ["", "## Ghost tracks (matched to no object: static truth)", "",
             "| track group | rows | tracks | false dyn z | false dyn speed |", "|---|---|---|---|---|"]
    for g, m in metrics.get("ghost", {}).items():
        lines.append(f"| {g} | {m['n']} | {m['n_tracks']} | {_ci(m, 'false_dynamic_z')} | "
                     f"{_ci(m, 'false_dynamic_speed')} |")
        if set(m.get("on", {})) - {NOTHING_LABELLED}:  # labelled objects that are no road user (nuScenes)
            for what, w in m["on"].items():
                lines.append(f"| {g} on {what} | {w['n']} | {w['n_tracks']} | {_ci(w, 'false_dynamic_z')} | "
                             f"{_ci(w, 'false_dynamic_speed')} |")
    lines += ["", "## At equal false alarms", "",
              "Each rule's missed-dynamic rate at the other rule's false-dynamic rate (z / alpha and speed / class "
              "threshold each swept over one factor).", "",
              "| group | FD speed | MD z at FD speed | MD speed | FD z | MD speed at FD z | MD z |",
              "|---|---|---|---|---|---|---|"]
    for g, m in metrics.get("matched", {}).items():
        lines.append(f"| {g} | {_fmt(m['false_dynamic_speed'])} | {_fmt(m['missed_dynamic_z_at_speed_false_dynamic'])}"
                     f" | {_fmt(m['missed_dynamic_speed'])} | {_fmt(m['false_dynamic_z'])} | "
                     f"{_fmt(m['missed_dynamic_speed_at_z_false_dynamic'])} | {_fmt(m['missed_dynamic_z'])} |")
    lines += ["", "## By ground-truth attribute (90 % intervals over tracks)", "",
              "| attribute | rows | tracks | false dyn z | false dyn speed | missed dyn z | missed dyn speed |",
              "|---|---|---|---|---|---|---|"]
    for attr, m in metrics.get("by_attribute", {}).items():
        lines.append(f"| {attr} | {m['n']} | {m['n_tracks']} | {_ci(m, 'false_dynamic_z')} | "
                     f"{_ci(m, 'false_dynamic_speed')} | {_ci(m, 'missed_dynamic_z')} | {_ci(m, 'missed_dynamic_speed')} |")
    if metrics.get("by_run"):
        lines += ["", "## Each pooled run (seed or scene; no intervals: a run is a handful of tracks)", "",
                  "| run | group | n static | n dynamic | false dyn z | false dyn speed | missed dyn z "
                  "| missed dyn speed | ghost rows | ghost false dyn z | ghost false dyn speed |",
                  "|---|---|---|---|---|---|---|---|---|---|---|"]
        for tag, entry in metrics["by_run"].items():
            for g, m in entry.items():
                lines.append(f"| {tag} | {g} | {m['n_static']} | {m['n_dynamic']} | {_fmt(m['false_dynamic_z'])} | "
                             f"{_fmt(m['false_dynamic_speed'])} | {_fmt(m['missed_dynamic_z'])} | "
                             f"{_fmt(m['missed_dynamic_speed'])} | {m['ghost_n']} | "
                             f"{_fmt(m['ghost_false_dynamic_z'])} | {_fmt(m['ghost_false_dynamic_speed'])} |")
    lines += ["", "## Rows whose window has filled", "",
              "| group | n static | n dynamic | false dyn z | false dyn speed | missed dyn z | missed dyn speed |",
              "|---|---|---|---|---|---|---|"]
    for g, m in metrics.get("full_window", {}).items():
        lines.append(f"| {g} | {m['n_static']} | {m['n_dynamic']} | {_ci(m, 'false_dynamic_z')} | "
                     f"{_ci(m, 'false_dynamic_speed')} | {_ci(m, 'missed_dynamic_z')} | {_ci(m, 'missed_dynamic_speed')} |")
    return lines


def write_outputs(out: Path, rec: Records, metrics: dict[str, Any],
                  detection_report: dict[str, Any] | None = None) -> dict[str, Any]:
    """Write figures, metrics.json (with the alpha sweep added) and report.md into ``out``; with the detector
    in the loop (``detection_report``, whose summary is already ``metrics["detection"]``) its figures too."""
    out.mkdir(parents=True, exist_ok=True)
    mode = metrics["run"].get("mode") or "z_test"  # the figures name the test that decided, as the text does
    plot_speed_vs_z(rec, out / "speed_vs_z.png", mode)
    plot_pr(rec, out / "pr_curves.png", mode)
    metrics["alpha_sweep"] = plot_alpha_sweep(rec, out / "alpha_sweep.png")
    has_cal = plot_calibration(metrics.get("calibration"), out / "calibration.png")
    det_figures = plot_detection(detection_report, out) if detection_report is not None else []
    # a figure this run did not draw, left in the folder by an earlier run (with calibration on, or the detector
    # in the loop), would be taken for this run's: it goes
    drawn = {"calibration.png": has_cal, **{name: name in det_figures for name in DETECTION_FIGURES}}
    for name, ok in drawn.items():
        if not ok:
            (out / name).unlink(missing_ok=True)
    metrics = finite_json(metrics)
    # whole or not at all, as the figures: on a full disk a report.md cut at 4 KB had read as a complete report
    write_atomically(out / "metrics.json", (json.dumps(metrics, indent=2, sort_keys=True, allow_nan=False) + "\n").encode())
    run = metrics["run"]
    test = "χ² test (mode chi2: the `_z` columns are its decisions)" if run.get("mode") == "chi2" else "z-test"
    lines = [
        f"# jitterguard eval — {run['source']}",
        "",
        *([f"**No decision was made**: {run['no_decision']}. Every table below is empty.", ""]
          if run.get("no_decision") else []),
        f"Input `{run['input']}`, {_input_desc(run)}, seed {run['seed']}, {run['frames']} frames, "
        f"{run['rows']} (frame, track) rows, {run['matched_rows']} matched to ground truth "
        f"(≤ {run['match_distance_m']} m). Operating points: {test} alpha {run['alpha']} "
        f"(effective_n `{run.get('effective_n')}`, calibration `{run.get('calibration')}`"
        + (f" from `{run['calibration_file']}`" if run.get("calibration_file") else "") + ", H0 speed ≤ "
        f"{run.get('min_speed_mps')} m/s"
        + (f", window {run['window_size']} observations" if run.get("window_size") else "")
        + (f", one every {run['window_stride']} frames" if (run.get("window_stride") or 1) > 1 else "")
        + (f" (window_size at {run['window_reference_hz']:g} Hz, fewer on a slower stream, every k-th frame of a "
           "faster one)" if run.get("window_size") and run.get("window_reference_hz") else "")
        + (f", held {run['dynamic_hold_s_per_class']} s" if run.get("dynamic_hold_s_per_class") else "")
        + (f", view term {run['view_slide_m_per_class']} m" if run.get("view_slide_m_per_class") else "")
        + (f", jump veto ({_vetoed_desc(run.get('vetoed_rows') or {})})" if run.get("jump_veto") else "")
        + f"), speed threshold {run['velocity_threshold']} m/s, per class "
        f"{run.get('velocity_threshold_per_class')}"
        + (f", sustain {run['velocity_sustain_s_per_class']} s" if run.get("velocity_sustain_s_per_class") else "")
        + ("; no position covariance reported" if run.get("variance_scale", 1.0) == 0.0
           else f"; every reported variance ×{run['variance_scale']:g}" if run.get("variance_scale", 1.0) != 1.0 else "")
        + f". Scored rows: matched, z-test window ≥ {run['min_window']}. Brackets: 90 % intervals over tracks. "
        "Times: the median over the (track, object) pairs that ever got it right, with the share that never did.",
        "",
        "| group | n static | n dynamic | AP z | AP speed | false dyn z | false dyn speed | missed dyn z "
        "| missed dyn speed | first correct z [s] | first correct speed [s] | moving → dynamic z [s] "
        "| moving → dynamic speed [s] |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for g, m in metrics["motion"].items():
        lines.append(
            f"| {g} | {m['n_static']} | {m['n_dynamic']} | {_ci(m, 'ap_z')} | {_ci(m, 'ap_speed')} | "
            f"{_ci(m, 'false_dynamic_z')} | {_ci(m, 'false_dynamic_speed')} | {_ci(m, 'missed_dynamic_z')} | "
            f"{_ci(m, 'missed_dynamic_speed')} | {_latency(m, 'first_correct', 'correct', 'z')} | "
            f"{_latency(m, 'first_correct', 'correct', 'speed')} | {_latency(m, 'dynamic', 'dynamic', 'z')} | "
            f"{_latency(m, 'dynamic', 'dynamic', 'speed')} |")
    lines += planner_lines(metrics)
    if metrics.get("alpha_from_labels"):
        lines += ["", "Alpha from labels (missed dynamic ≤ 5 %; a diagnostic, never used at run time): "
                  + ", ".join(f"{g} {_fmt(a)}" for g, a in metrics["alpha_from_labels"].items())]
    lines += ["", "![speed vs z](speed_vs_z.png)", "", "![PR curves](pr_curves.png)", "",
              "![alpha sweep](alpha_sweep.png)", ""]
    if has_cal:
        lines += ["![variance calibration](calibration.png)", ""]
    if metrics.get("detection") is not None:
        lines += detection_lines(metrics["detection"], det_figures) + [""]
    write_atomically(out / "report.md", "\n".join(lines).encode())
    return metrics
