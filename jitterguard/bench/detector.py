"""``jitterguard bench detector``: end-to-end detector time per HDL-32E scan, per preset.

What is timed is exactly :meth:`Detector.detect` on one scan — voxelisation into pillars, the network (pillar
encoder, scatter, SECOND backbone, FPN neck, heads), decoding (peaks, top-K, boxes) and per-class circle NMS —
on real ray-cast HDL-32E scans of a synthetic scenario (:func:`jitterguard.services.detector.data.synthetic_samples`),
after untimed warm-up scans. Ray casting, Zenoh and message building are not included: they are the replay's and
the adapter's cost. torch uses ``threads`` intra-op threads (default: every core of the machine), because a
deployed detector owns its cores.

Weights do not change the network's cost, only how many candidates pass the score threshold into NMS; a
randomly initialised network (no shipped weights) passes many, so its decode time is an upper bound. Each
preset's row says which weights it ran. ``p99_ms`` over a few dozen scans is close to the maximum.

``cpu_p50_ms`` is the process's CPU time per scan (all threads summed; OpenMP's spin-waiting counts too). On a
shared, busy machine wall time measures the neighbours as much as the detector; with ``--threads 1`` the CPU
time is what a scan costs one otherwise idle core, the figure to compare across runs. The CLI runs with
``OMP_WAIT_POLICY=PASSIVE`` unless the environment sets it (as the service does; see ``cli.passive_openmp``).
"""

from __future__ import annotations

import os
import statistics
import sys
import time
from collections.abc import Iterable, Mapping, Sequence
from typing import Any, TypeVar

import numpy as np

from ..services.detector.config import PRESETS
from ..sim.world import SCENARIO_NAMES as SCENARIOS  # the world's own list (loading-street had been missing)
STAGES = ("voxelize", "network", "decode")
T = TypeVar("T")


def _bar(it: Iterable[T], total: int, desc: str, enabled: bool) -> Iterable[T]:
    """tqdm on stderr (stdout stays clean JSON)."""
    if not enabled:
        return it
    from tqdm import tqdm  # type: ignore[import-untyped]  # only when a bar is asked for

    return tqdm(it, total=total, desc=desc, unit="scan", file=sys.stderr, leave=False)


def bench_scans(n: int, scenario: str = "mixed", seed: int = 0, progress: bool = False,
                sweeps: int = 1) -> list[np.ndarray]:
    """``n`` HDL-32E scans (P, 4) spread over a scenario long enough that they are not near-duplicates; with
    ``sweeps`` > 1, (P, 5) stacks of that many sweeps (:func:`~jitterguard.services.detector.data.synthetic_samples`)."""
    from ..services.detector.data import synthetic_samples  # torch: the optional "torch" extra

    duration = max(4.0, n / 2.0)  # 10 Hz: every 5th frame at most
    samples = synthetic_samples([scenario], [seed], frames_per_scenario=n, duration_s=duration, sweeps=sweeps)
    return [s.points for s in _bar(samples, n, "ray-casting scans", progress)]


def percentile(values: Sequence[float], q: float) -> float:
    """Linear-interpolated percentile (numpy's default), as a float."""
    return float(np.percentile(np.asarray(values, dtype=np.float64), q))


def _row(timed: Sequence[np.ndarray], total: list[float], cpu: list[float], stages: dict[str, list[float]],
         found: list[int]) -> dict[str, Any]:
    return {
        "points": round(float(np.mean([len(p) for p in timed])), 1),
        "p50_ms": round(percentile(total, 50), 2),
        "p99_ms": round(percentile(total, 99), 2),
        "mean_ms": round(statistics.fmean(total), 2),
        "cpu_p50_ms": round(percentile(cpu, 50), 2),
        "stages_ms": {s: round(statistics.median(v), 2) for s, v in stages.items()},
        "detections": round(statistics.fmean(found), 1),
        "scans": len(timed),
    }


def time_preset(detector: Any, scans: Sequence[np.ndarray], warmup: int, desc: str = "",
                progress: bool = False) -> dict[str, Any]:
    """Per-scan end-to-end times of ``detector.detect`` over ``scans`` (the first ``warmup`` untimed)."""
    return time_backends({"": detector}, scans, warmup, desc, progress)[""]


def time_backends(detectors: Mapping[str, Any], scans: Sequence[np.ndarray], warmup: int, desc: str = "",
                  progress: bool = False) -> dict[str, dict[str, Any]]:
    """:func:`time_preset` for several detectors of one network at once, interleaved: every scan goes through each
    detector back to back (the order rotating from scan to scan), so a change in the machine's load lands on all
    of them alike and their ratio is measured under the same conditions."""
    names = list(detectors)
    for pts in scans[:warmup]:
        for n in names:
            detectors[n].detect(pts)
    timed = scans[warmup:]
    total: dict[str, list[float]] = {n: [] for n in names}
    cpu: dict[str, list[float]] = {n: [] for n in names}
    stages: dict[str, dict[str, list[float]]] = {n: {s: [] for s in STAGES} for n in names}
    found: dict[str, list[int]] = {n: [] for n in names}
    for i, pts in enumerate(_bar(timed, len(timed), desc, progress)):
        for n in names[i % len(names):] + names[: i % len(names)]:
            det = detectors[n]
            c0, t0 = time.process_time(), time.perf_counter()
            out = det.detect(pts)
            total[n].append((time.perf_counter() - t0) * 1e3)
            cpu[n].append((time.process_time() - c0) * 1e3)
            for s in STAGES:
                stages[n][s].append(float(det.timings.get(s, float("nan"))))
            found[n].append(len(out))
    return {n: _row(timed, total[n], cpu[n], stages[n], found[n]) for n in names}


def available_backends() -> tuple[str, ...]:
    """torch always; onnxruntime when it and the ONNX exporter's packages are installed."""
    import importlib.util

    have = all(importlib.util.find_spec(m) is not None for m in ("onnxruntime", "onnx", "onnxscript"))
    return ("torch", "onnxruntime") if have else ("torch",)


def run(presets: Sequence[str], *, scans: int = 40, warmup: int = 3, threads: int | None = None,
        weights: Mapping[str, str] | None = None, scenario: str = "mixed", seed: int = 0,
        progress: bool = True, backends: Sequence[str] = ("torch",), device: str = "cpu",
        sweeps: int = 1, flips: bool = False) -> dict[str, dict[str, Any]]:
    """``{preset: {"points", "p50_ms", "p99_ms", "mean_ms", "cpu_p50_ms", "stages_ms", "detections", "scans",
    "threads", "weights", "omp_wait_policy"}}`` — the same scans for every preset — for the torch backend.

    With ``"onnxruntime"`` in ``backends`` the preset's network is exported to ONNX (in a temporary folder) and
    timed in the same process on the same scans, interleaved with torch scan by scan (:func:`time_backends`); its
    row goes under ``"onnxruntime"`` in the preset's row, with ``"onnxruntime_over_torch_p50"`` (< 1: faster).
    ``sweeps`` > 1 times stacks of that many sweeps (20 Hz, one spin apart at most) on five-field networks: weights
    trained on stacks as they are, single-sweep ones widened by a zero time-lag input (``network.with_time_lag``:
    the cost of a stacked model whatever it learnt); each row names its sweeps.
    ``device`` ``cuda`` runs torch's voxelisation and network on the GPU (onnxruntime stays on the CPU); each
    row names its device. ``flips`` times the detector with test-time flips (four passes of the network per scan,
    on either backend); each row says whether it ran them."""
    import tempfile  # only with --backends onnxruntime

    import torch  # the optional "torch" extra, after passive_openmp() has set OpenMP's policy

    from ..services.detector.inference import Detector, WeightsError, shipped_weights  # torch, as above

    unknown = [p for p in presets if p not in PRESETS]
    if unknown:
        raise ValueError(f"unknown preset(s) {unknown}; expected some of {list(PRESETS)}")
    bad = [b for b in backends if b not in ("torch", "onnxruntime")]
    if bad or "torch" not in backends:
        raise ValueError(f"backends must include torch and be some of torch, onnxruntime; got {list(backends)}")
    weights = dict(weights or {})
    n_threads = threads or os.cpu_count() or 1
    data = bench_scans(warmup + scans, scenario, seed, progress, sweeps)
    out: dict[str, dict[str, Any]] = {}
    for name in presets:
        det = Detector.load(weights.get(name), name, threads=n_threads, device=device, flips=flips)
        if det.config.name != name:  # a weights file fixes its network: never time one under another's name
            raise WeightsError(f"{weights.get(name)} is a {det.config.name!r} network, not {name!r}")
        widened = sweeps > 1 and det.config.num_point_features == 4
        if widened:
            from ..services.detector.network import with_time_lag

            det = Detector(with_time_lag(det.model.cpu()), recalibration=det.recalibration, threads=n_threads,
                           meta={"source": {"sweeps": sweeps}}, self_crop=det.self_crop, device=device, flips=flips)
        torch.set_num_threads(n_threads)  # the same for every preset, whatever a previous load did
        if name in weights:
            which = weights[name]
        elif shipped_weights(name).is_file():
            which = "shipped"
        else:
            which = "random-init"
        if widened:
            which += " (+ zero time-lag input)"
        common = {"threads": n_threads, "weights": which, "device": _device_name(device), "sweeps": sweeps, "flips": flips,
                  "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY", "default")}
        if "onnxruntime" not in backends:
            row = time_preset(det, data, warmup, f"timing {name}", progress)
            row.update(common)
            out[name] = row
            continue
        from ..services.detector.onnx_backend import load_onnx_detector  # onnxruntime: the optional "onnx" extra
        from ..services.detector.onnx_export import export_onnx

        with tempfile.TemporaryDirectory(prefix="jitterguard-bench-onnx-") as tmp:
            export_onnx(det.model, tmp, recalibration=det.recalibration)
            ort_det = load_onnx_detector(tmp, threads=n_threads, flips=flips)
            torch.set_num_threads(n_threads)
            rows = time_backends({"torch": det, "onnxruntime": ort_det}, data, warmup,
                                 f"timing {name} (torch, onnxruntime)", progress)
        row = {**rows["torch"], **common, "backend": "torch"}
        row["onnxruntime"] = {**rows["onnxruntime"], **common, "device": "cpu", "backend": "onnxruntime", "layout": "single",
                              "onnxruntime_version": _ort_version()}
        row["onnxruntime_over_torch_p50"] = round(rows["onnxruntime"]["p50_ms"] / rows["torch"]["p50_ms"], 3)
        out[name] = row
    return out


def _ort_version() -> str:
    import onnxruntime

    return str(onnxruntime.__version__)


def _device_name(device: str) -> str:
    """``cpu``, or ``cuda (NVIDIA H200)``: a GPU timing is only comparable on the same card."""
    import torch

    dev = torch.device(device)
    return f"cuda ({torch.cuda.get_device_name(dev)})" if dev.type == "cuda" else "cpu"
