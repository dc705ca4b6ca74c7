"""Bird's-eye-view rendering of a scan with its ground-truth boxes, for eyeballing that a scene is plausible.

Colour encodes the ground-truth motion state, the quantity jitterguard is about: red = moving, orange =
temporarily at rest (vehicle.stopped, pedestrian.standing, a cyclist waiting), blue = parked / sitting / a bicycle
without rider. Points are shaded by height. Rendering needs matplotlib (Agg backend; no display).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from ..files import save_figure
from .world import SENSOR_HEIGHT_M, GroundTruthFrame

MOVING = "#d62728"
RESTING = "#ff9f1c"
PARKED = "#1f77b4"
_PARKED_ATTRS = ("vehicle.parked", "pedestrian.sitting_lying_down", "cycle.without_rider")


def state_colour(attribute: str, moving: bool) -> str:
    if moving:
        return MOVING
    return PARKED if attribute in _PARKED_ATTRS else RESTING


def render_bev(frame: GroundTruthFrame, points: NDArray[np.float32], path: str, *, extent_m: float = 50.0,
               title: str | None = None, dpi: int = 150) -> None:
    """Write a PNG of ``points`` (sensor frame) and ``frame``'s boxes, ego-centred, ±``extent_m`` metres."""
    import matplotlib  # only when a picture is drawn (start-up time); the Agg backend is chosen first

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D
    from matplotlib.patches import Polygon

    fig, ax = plt.subplots(figsize=(9, 9))
    ax.set_facecolor("#0b0b10")
    z = points[:, 2] + SENSOR_HEIGHT_M
    near = (np.abs(points[:, 0]) < extent_m) & (np.abs(points[:, 1]) < extent_m)
    order = np.argsort(z[near])
    ax.scatter(points[near, 0][order], points[near, 1][order], c=z[near][order], s=1.2,
               cmap="turbo", vmin=-0.2, vmax=4.0, linewidths=0, alpha=0.9, zorder=3)
    c, s = math.cos(frame.ego_yaw), math.sin(frame.ego_yaw)
    for n in range(frame.num_objects):
        dx, dy = frame.centers[n, 0] - frame.ego_x, frame.centers[n, 1] - frame.ego_y
        x, y = c * dx + s * dy, -s * dx + c * dy
        if abs(x) > extent_m + 5 or abs(y) > extent_m + 5:
            continue
        yaw = frame.yaws[n] - frame.ego_yaw
        L, W = frame.sizes[n, 0], frame.sizes[n, 1]
        cy, sy = math.cos(yaw), math.sin(yaw)
        corners = [(x + cy * a * L / 2 - sy * b * W / 2, y + sy * a * L / 2 + cy * b * W / 2)
                   for a, b in ((1, 1), (1, -1), (-1, -1), (-1, 1))]
        col = state_colour(frame.attributes[n], bool(frame.moving[n]))
        ax.add_patch(Polygon(corners, closed=True, fill=False, edgecolor=col, linewidth=0.9, alpha=0.85,
                             zorder=2))
        ax.plot([x, x + cy * L / 2], [y, y + sy * L / 2], color=col, linewidth=0.8)  # heading
        if frame.moving[n]:
            vx, vy = frame.velocities[n]
            ax.arrow(x, y, (c * vx + s * vy) * 0.5, (-s * vx + c * vy) * 0.5, color=col, width=0.05,
                     head_width=0.5, length_includes_head=True)
    ax.add_patch(Polygon([(2.35, 0.95), (2.35, -0.95), (-2.35, -0.95), (-2.35, 0.95)], closed=True, fill=True,
                         facecolor="white", edgecolor="white"))
    ax.set_xlim(-extent_m, extent_m)
    ax.set_ylim(-extent_m, extent_m)
    ax.set_aspect("equal")
    ax.set_xlabel("x forward (m)")
    ax.set_ylabel("y left (m)")
    handles = [Line2D([0], [0], color=MOVING, lw=2, label="moving"),
               Line2D([0], [0], color=RESTING, lw=2, label="stopped / standing"),
               Line2D([0], [0], color=PARKED, lw=2, label="parked / sitting / no rider"),
               Line2D([0], [0], color="white", lw=6, label="ego")]
    ax.legend(handles=handles, loc="upper right", fontsize=8, facecolor="#222222", labelcolor="white")
    ax.set_title(title or f"frame {frame.seq}: {len(points)} points, {frame.num_objects} objects")
    fig.tight_layout()
    try:
        save_figure(fig, path, dpi=dpi)
    finally:
        plt.close(fig)
