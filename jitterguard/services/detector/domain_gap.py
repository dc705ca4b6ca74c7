"""How real scans differ from synthetic ones: the measurements behind the sim-to-real effects
(``jitterguard domain-gap``, docs/detector.md "The sim-to-real gap").

Pure numpy over :class:`~.config.Sample` lists (sensor frame): per range band the returns per scan, split into
ground-level (below ``ground_z`` in the sensor frame) and above, the intensity percentiles, the returns inside
car boxes and how they spread over the box height, and the height of the lowest returns (the road surface) per
azimuth sector and range band — the sloped ground that made the first detector fire on empty road.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ...files import save_figure
from .augment import points_in_boxes
from .config import CLASS_NAMES, Sample

BANDS_M: tuple[tuple[float, float], ...] = ((1, 5), (5, 10), (10, 20), (20, 30), (30, 40), (40, 50), (50, 70))
SECTOR_BANDS_M: tuple[tuple[float, float], ...] = ((3, 6), (6, 10), (10, 15), (15, 20), (20, 30), (30, 40), (40, 50))
MIN_RANGE_M = 1.0
"""Returns closer than this are the sensor's own no-return placeholders and body (nuScenes keeps ~10k per scan)."""


def _pct(v: NDArray[np.floating], q: Sequence[float]) -> list[float] | None:
    return [float(x) for x in np.percentile(v, q)] if len(v) else None


def scan_statistics(samples: Sequence[Sample], *, ground_z: float = -1.45, car_band: tuple[float, float] = (8, 25),
                    max_boxes_per_scan: int = 200) -> dict[str, Any]:
    """The statistics of one set of scans (see the module doc); ``samples`` need boxes only for the per-car
    figures."""
    n = len(samples)
    per_band: list[dict[str, Any]] = []
    tot = np.zeros(len(BANDS_M))
    gr = np.zeros(len(BANDS_M))
    inten: list[list[NDArray[np.float32]]] = [[] for _ in BANDS_M]
    car_pts: list[list[int]] = [[] for _ in BANDS_M]
    hz: list[NDArray[np.float64]] = []
    car_int: list[NDArray[np.float32]] = []
    sector_low: list[NDArray[np.float64]] = []
    car = CLASS_NAMES.index("car")
    for s in samples:
        p = s.points[np.linalg.norm(s.points[:, :3], axis=1) >= MIN_RANGE_M]
        r = np.hypot(p[:, 0], p[:, 1])
        for i, (lo, hi) in enumerate(BANDS_M):
            m = (r >= lo) & (r < hi)
            tot[i] += m.sum()
            gr[i] += (m & (p[:, 2] < ground_z)).sum()
            inten[i].append(p[m, 3])
        boxes = s.boxes[s.labels == car][:max_boxes_per_scan]
        if len(boxes):
            inside = points_in_boxes(p, boxes)
            counts = inside.sum(axis=0)
            rb = np.hypot(boxes[:, 0], boxes[:, 1])
            for i, (lo, hi) in enumerate(BANDS_M):
                car_pts[i].extend(counts[(rb >= lo) & (rb < hi)].tolist())
            for j in np.flatnonzero((rb >= car_band[0]) & (rb < car_band[1]) & (counts >= 5)):
                q = p[inside[:, j]]
                hz.append((q[:, 2] - (boxes[j, 2] - boxes[j, 5] / 2)) / boxes[j, 5])
                car_int.append(q[:, 3])
        off = np.ones(len(p), bool)
        if len(s.boxes):
            off = ~points_in_boxes(p, s.boxes, 0.3).any(axis=1)
        sector_low.append(_sector_lows(p[off]))
    for i, (lo, hi) in enumerate(BANDS_M):
        iv = np.concatenate(inten[i]) if inten[i] else np.zeros(0)
        cp = np.asarray(car_pts[i])
        per_band.append({
            "band_m": [lo, hi], "returns_per_scan": tot[i] / max(n, 1), "ground_per_scan": gr[i] / max(n, 1),
            "above_ground_per_scan": (tot[i] - gr[i]) / max(n, 1), "intensity_p10_50_90": _pct(iv, (10, 50, 90)),
            "cars": int(len(cp)), "returns_per_car_median": float(np.median(cp)) if len(cp) else None,
            "cars_without_returns": float(np.mean(cp == 0)) if len(cp) else None,
        })
    prof = None
    if hz:
        h, _ = np.histogram(np.concatenate(hz), bins=np.linspace(0, 1, 11))
        prof = (h / max(h.sum(), 1)).tolist()
    lows = np.stack(sector_low) if sector_low else np.zeros((0, 8, len(SECTOR_BANDS_M)))
    with np.errstate(all="ignore"):
        spread = np.nanpercentile(lows, [5, 50, 95], axis=(0, 1)) if len(lows) else None
    return {
        "scans": n,
        "valid_returns_per_scan": float(tot.sum() / max(n, 1)),
        "bands": per_band,
        "car_height_profile": prof,
        "car_height_profile_band_m": list(car_band),
        "car_intensity_p10_50_90": _pct(np.concatenate(car_int), (10, 50, 90)) if car_int else None,
        "road_height_sector_bands_m": [list(b) for b in SECTOR_BANDS_M],
        "road_height_p5_50_95": None if spread is None else [[None if not np.isfinite(v) else float(v) for v in row]
                                                               for row in spread],
    }


def _sector_lows(p: NDArray[np.float32]) -> NDArray[np.float64]:
    """(8 sectors of 45°, range bands) the 3rd-percentile height of the returns: where the road surface is."""
    r = np.hypot(p[:, 0], p[:, 1])
    az = np.degrees(np.arctan2(p[:, 1], p[:, 0]))
    out = np.full((8, len(SECTOR_BANDS_M)), np.nan)
    for a in range(8):
        ma = (az >= -180 + 45 * a) & (az < -135 + 45 * a)
        for b, (lo, hi) in enumerate(SECTOR_BANDS_M):
            m = ma & (r >= lo) & (r < hi)
            if m.sum() > 20:
                out[a, b] = np.percentile(p[m, 2], 3)
    return out


def comparison_plot(stats: dict[str, dict[str, Any]], path: str) -> None:
    """Four panels, one line per data set: returns per scan (ground / above) per range band, returns per car,
    car height profile, road height spread per range band."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 4, figsize=(20, 4.4))
    for name, st in stats.items():
        mid = [np.mean(b["band_m"]) for b in st["bands"]]
        line = ax[0].plot(mid, [b["ground_per_scan"] for b in st["bands"]], "-o", label=f"{name} ground")[0]
        ax[0].plot(mid, [b["above_ground_per_scan"] for b in st["bands"]], "--o", color=line.get_color(),
                   label=f"{name} above")
        cars = [(m, b["returns_per_car_median"]) for m, b in zip(mid, st["bands"]) if b["returns_per_car_median"]]
        if cars:
            ax[1].plot(*zip(*cars), "-o", color=line.get_color(), label=name)
        if st["car_height_profile"]:
            ax[2].plot(np.arange(0.05, 1.0, 0.1), st["car_height_profile"], "-o", color=line.get_color(), label=name)
        if st["road_height_p5_50_95"]:
            sb = [np.mean(b) for b in st["road_height_sector_bands_m"]]
            lo, med, hi = (np.array(row, dtype=float) for row in st["road_height_p5_50_95"])
            ax[3].fill_between(sb, lo, hi, color=line.get_color(), alpha=0.2)
            ax[3].plot(sb, med, "-o", color=line.get_color(), label=name)
    ax[0].set(xlabel="range [m]", ylabel="returns per scan", yscale="log", title="returns (ground: z < −1.45 m)")
    ax[1].set(xlabel="range [m]", ylabel="median returns per car", yscale="log", title="returns on cars")
    ax[2].set(xlabel="height in the box (0 bottom, 1 top)", ylabel="fraction of a car's returns",
              title="where cars return (8–25 m)")
    ax[3].set(xlabel="range [m]", ylabel="z of the lowest returns [m]", title="road height, 5–95 % over sectors")
    for a in ax:
        a.grid(alpha=0.3)
        a.legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, path, dpi=90)
    plt.close(fig)
