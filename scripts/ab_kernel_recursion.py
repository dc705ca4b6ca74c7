"""Back to back in one process: the calibrated statistic's correlation kernel as a base checkout applied it (dense
W × W kernels, computed once per distinct time pattern) against this tree's forward/backward passes
(docs/performance.md, "The correlation kernel by recursion"), inside the whole classifier core, frame by frame
alternating, on three streams of 10 / 100 / 1000 tracks at 10 Hz with the window of 20:

* ``bench``: the core bench's stream (``jitterguard bench classifier --core-only``: 5 % of observations missed);
* ``dropout``: the same with 30 % missed (every window its own pattern of gaps);
* ``eval``: what the evaluator's tracker hands the classifier (``diagonal-lot``, seed 0, noise model), with
  extra copies of each track whose observations are missed at 5 % of their own, to reach the track count.

    git worktree add /tmp/base <rev>     # a commit before the recursion, e.g. 8c8e50d
    OMP_NUM_THREADS=1 .venv/bin/python scripts/ab_kernel_recursion.py [--base /tmp/base] [--sizes 10,100,1000]

Prints JSON: per stream and size, the share of windows with a distinct time pattern and (median, mean, p99) ms
per ``update`` for both, with ``calibration: file`` (the statistic alone) and the default (online learning too);
every frame's decisions are checked equal between the two."""
from __future__ import annotations

import argparse
import json
import sys
import time
import types
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from jitterguard.bench.classifier import _Scene  # noqa: E402
from jitterguard.schemas.models import ClassifierConfig  # noqa: E402
from jitterguard.services.classifier import statistics as stats_mod  # noqa: E402
from jitterguard.services.classifier.calibration import NoiseModel  # noqa: E402
from jitterguard.services.classifier.core import MotionClassifierCore, Observations  # noqa: E402


def _base_kernels(base: Path) -> dict:
    """The base checkout's statistics module, run from its source against this tree's calibration module."""
    src = (base / "jitterguard/services/classifier/statistics.py").read_text()
    src = src.replace("from .calibration import", "from jitterguard.services.classifier.calibration import")
    module = types.ModuleType("base_statistics")
    sys.modules[module.__name__] = module  # dataclasses look their module up
    exec(compile(src, str(base / "statistics.py"), "exec"), module.__dict__)  # noqa: S102 - a local checkout
    ns = module.__dict__
    if "correlation_kernels" not in ns:
        raise SystemExit(f"{base} has no correlation_kernels: give a checkout from before the recursion")
    return ns


class _Switch:
    """Routes the statistic's kernel products to the base or to this tree's implementation."""

    def __init__(self, base: dict) -> None:
        self.base, self.mode, self.ctx = base, "new", (None, None)
        self.recursion = stats_mod.exponential_kernel_products
        self.calibrated = stats_mod._calibrated_statistics

    def install(self) -> None:
        def calibrated(windows, masks, groups, model, **kw):  # noqa: ANN001, ANN202
            self.ctx = (groups, model)
            return self.calibrated(windows, masks, groups, model, **kw)

        def products(t, valid, tau, rows):  # noqa: ANN001, ANN202
            if self.mode == "new":
                return self.recursion(t, valid, tau, rows)
            phi, phi_sq = self.base["correlation_kernels"](t, valid, *self.ctx)
            return np.stack([phi.times(k, rows[k]) for k in range(2)]), np.stack(phi_sq)

        stats_mod._calibrated_statistics = calibrated
        stats_mod.exponential_kernel_products = products


def _eval_stream() -> list[Observations]:
    from jitterguard.eval.pipeline import NOISE_PRESETS, run_pipeline
    from jitterguard.sim.world import make_scenario

    frames: list[Observations] = []
    update = MotionClassifierCore.update

    def capture(self, obs):  # noqa: ANN001, ANN202
        frames.append(obs)
        return update(self, obs)

    MotionClassifierCore.update = capture
    try:
        run_pipeline(make_scenario("diagonal-lot", 0, 15.0, 10.0), NOISE_PRESETS["jittery"](), 0, ClassifierConfig())
    finally:
        MotionClassifierCore.update = update
    return frames[::2]  # the pipeline runs two cores (z-test, threshold) on the same frames


def _widen(frames: list[Observations], tracks: int, seed: int) -> list[Observations]:
    per = max(1.0, np.mean([len(o.track_ids) for o in frames]))
    copies = max(1, round(tracks / per))
    rng = np.random.default_rng(seed)

    def tag(ids: np.ndarray, j: int) -> np.ndarray:
        return np.array([f"{j:02x}".encode() + i[2:] for i in ids.tolist()], dtype="S32")

    out = []
    for o in frames:
        n = len(o.track_ids)
        keep = np.concatenate([np.ones(n, bool)] + [rng.random(n) > 0.05 for _ in range(copies - 1)])
        cols = {f: np.concatenate([getattr(o, f)] * copies)[keep] for f in ("labels", "x", "y", "cxx", "cxy", "cyy", "speed")}
        ids = np.concatenate([tag(o.track_ids, j) for j in range(copies)])[keep]
        pub = None if o.published_ids is None else np.concatenate([tag(o.published_ids, j) for j in range(copies)])
        out.append(replace(o, track_ids=ids, published_ids=pub, **cols))
    return out


def _distinct_patterns(frames: list[Observations], window: int) -> float:
    """Share of windows whose time pattern (stamps relative to the first, slots) no other window of the frame has."""
    core = MotionClassifierCore(ClassifierConfig(window_size=window, calibration="file", calibration_file="x.yaml"),
                                capacity=64, calibration_model=NoiseModel.prior())
    shares = []
    for i, o in enumerate(frames):
        core.update(o)
        if i >= 3 * window:
            t = core._table
            rows = core._id_rows
            win = t.ordered(rows, t.window)
            valid = np.arange(t.window)[None, :] >= t.window - t.count[rows][:, None]
            rel = np.where(valid, win[..., 5] - np.where(valid, win[..., 5], np.inf).min(1, keepdims=True), -1.0)
            shares.append(len(np.unique(np.round(rel, 6), axis=0)) / max(1, len(rows)))
    return float(np.mean(shares)) if shares else float("nan")


def _time(frames: list[Observations], switch: _Switch, window: int) -> dict:
    out = {}
    for label, cfg, model in (
            ("file", ClassifierConfig(window_size=window, calibration="file", calibration_file="x.yaml"), NoiseModel.prior()),
            ("default", ClassifierConfig(window_size=window), None)):
        cores = {m: MotionClassifierCore(cfg, capacity=64, calibration_model=model) for m in ("base", "new")}
        times: dict[str, list[float]] = {m: [] for m in cores}
        for i, o in enumerate(frames):
            got = {}
            for m, core in cores.items():
                switch.mode = m
                t0 = time.perf_counter()
                got[m] = core.update(o)
                core.learn()
                if i >= 3 * window:
                    times[m].append((time.perf_counter() - t0) * 1e3)
            if not np.array_equal(got["base"].state, got["new"].state):
                raise SystemExit(f"decisions differ at frame {i}")
        out[label] = {m: [round(float(np.median(v)), 2), round(float(np.mean(v)), 2),
                          round(float(np.percentile(v, 99)), 2)] for m, v in times.items()}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--base", type=Path, default=Path("/tmp/base"))
    ap.add_argument("--sizes", default="10,100,1000")
    ap.add_argument("--frames", type=int, default=200)
    ap.add_argument("--streams", default="bench,dropout,eval")
    args = ap.parse_args()
    switch = _Switch(_base_kernels(args.base))
    window = ClassifierConfig().window_size
    recorded = _eval_stream() if "eval" in args.streams else []
    switch.install()
    result = {}
    for n in (int(s) for s in args.sizes.split(",")):
        def frames_of(scene: _Scene) -> list[Observations]:  # one scene: its misses are drawn frame by frame
            return [scene.frame(k) for k in range(args.frames + 3 * window)]

        streams = {"bench": lambda: frames_of(_Scene(n, 0)), "dropout": lambda: frames_of(_Scene(n, 0, missed=0.3)),
                   "eval": lambda: _widen(recorded, n, 0)}
        for name in args.streams.split(","):
            frames = streams[name]()
            row = {"tracks_per_frame": round(float(np.mean([len(o.track_ids) for o in frames])), 1),
                   "distinct_pattern_share": round(_distinct_patterns(frames, window), 2)}
            row.update(_time(frames, switch, window))
            result[f"{name}_{n}"] = row
            print(json.dumps({f"{name}_{n}": row}), flush=True)
    print(json.dumps(result))


if __name__ == "__main__":
    main()
