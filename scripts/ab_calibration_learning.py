"""Back to back in one process: the online calibration's learning (block_moments + OnlineCalibration.add + the
refit when due) of a base checkout and of this tree, on the same blocks harvested from the classifier bench's
stream (docs/performance.md, "Pooling the calibration from factors" and "The calibration's learning compiled").

    git worktree add /tmp/base <rev>
    OMP_NUM_THREADS=1 .venv/bin/python scripts/ab_calibration_learning.py [TRACKS [prof]] [--base /tmp/base]

Prints per implementation three rounds of (median, mean, p99) ms per harvest, alternating, and how far the fitted
scales of the two differ (rounding only)."""
import importlib.util, inspect, sys, time, json, numpy as np
from pathlib import Path
BASE = sys.argv[sys.argv.index("--base") + 1] if "--base" in sys.argv else "/tmp/base"
sys.argv = [a for i, a in enumerate(sys.argv) if a != "--base" and (i == 0 or sys.argv[i - 1] != "--base")]
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import jitterguard.services.classifier.calibration as new_cal
# the base's module as a sibling of this tree's (its relative imports resolve to this tree's package)
name = "jitterguard.services.classifier._base_calibration"
spec = importlib.util.spec_from_file_location(name, f"{BASE}/jitterguard/services/classifier/calibration.py")
base_cal = importlib.util.module_from_spec(spec); sys.modules[name] = base_cal; spec.loader.exec_module(base_cal)
from jitterguard.bench.classifier import _Scene
from jitterguard.services.classifier.core import MotionClassifierCore
from jitterguard.schemas.models import ClassifierConfig
import jitterguard.services.classifier.core as core_mod
n = int(sys.argv[1]) if len(sys.argv) > 1 else 1000
captured = []
orig_add = new_cal.OnlineCalibration.add
orig_bm = core_mod.block_moments
cur = {}
def cap_bm(t, pos, cov, sensor, **kw):
    cur['in'] = (t.copy(), pos.copy(), cov.copy(), sensor.copy(), kw)
    return orig_bm(t, pos, cov, sensor, **kw)
def cap_add(self, groups, mom, young=None):
    captured.append((len(cur.get('frames', [])), cur['in'], np.asarray(groups).copy(), None if young is None else np.asarray(young).copy()))
    return orig_add(self, groups, mom, young)
core_mod.block_moments = cap_bm
new_cal.OnlineCalibration.add = cap_add
scene = _Scene(n, 0)
core = MotionClassifierCore(ClassifierConfig(), capacity=n)
for k in range(300):
    core.update(scene.frame(k)); core.learn()
core_mod.block_moments = orig_bm; new_cal.OnlineCalibration.add = orig_add
calls = captured[60:]  # after the first windows filled
print("harvest calls", len(calls), "blocks per call", np.mean([len(c[1][0]) for c in calls]))
def run(mod):
    cal = mod.OnlineCalibration(window=20); cal.advance(0.0)
    ts = []
    for i, ((t, pos, cov, sensor, kw), g, y) in enumerate((c[1], c[2], c[3]) for c in calls):
        cal.advance(float(t.max()))
        t0 = time.perf_counter()
        extra = {"skip_fast": True} if "skip_fast" in inspect.signature(mod.block_moments).parameters else {}
        mom = mod.block_moments(t, pos, cov, sensor, **kw, **extra)  # a base before 3 Dec skipped fast blocks so
        cal.add(g, mom, y)
        cal.model()
        ts.append(time.perf_counter() - t0)
    return np.array(ts) * 1e3, cal
res = {"base": [], "new": []}
for rep in range(3):
    for name, mod in (("base", base_cal), ("new", new_cal)):
        ts, cal = run(mod)
        res[name].append((float(np.median(ts)), float(ts.mean()), float(np.percentile(ts, 99))))
        if rep == 0: res[name + "_scale"] = cal.refit().scale
print(json.dumps({k: v for k, v in res.items() if not k.endswith("scale")}))
print("scales equal to", float(np.max(np.abs(res["base_scale"] - res["new_scale"]))))
if len(sys.argv) > 2:
    import cProfile, pstats
    pr = cProfile.Profile(); pr.enable(); run(new_cal); pr.disable()
    pstats.Stats(pr).sort_stats("tottime").print_stats(18)
