"""A minimal TF tree for bags and live TF: enough to give a point cloud its sensor pose in the world.

Real ROS 2 recordings rarely carry the LiDAR's world pose directly: ``/tf`` holds ``map → base_link`` from
localisation and ``/tf_static`` the chain ``base_link → … → lidar``. The replay contract wants the pose of
the cloud's own ``frame_id`` in the world, so the bag source composes the chain from the tree's root down to
that frame, interpolating each dynamic edge at the scan's stamp (linear position, slerp rotation) and
using static edges as they are. Pure: fed with (parent, child, stamp, pose) tuples, no rosbags here.
"""

from __future__ import annotations

import bisect

from ..frames import IDENTITY, EgoPose, compose
from .ros_types import interpolate_pose


class TfTree:
    """Edges child → parent; each child has exactly one parent (as tf2 requires)."""

    def __init__(self) -> None:
        self.parent: dict[str, str] = {}
        self.static: dict[str, EgoPose] = {}
        self._times: dict[str, list[int]] = {}
        self._poses: dict[str, list[EgoPose]] = {}
        self._sorted = True

    @staticmethod
    def _norm(frame: str) -> str:
        return frame.lstrip("/")  # ROS 1 habit: "/base_link" and "base_link" are the same frame

    def add(self, parent: str, child: str, stamp_ns: int, pose: EgoPose, *, static: bool = False) -> None:
        """Record the pose of ``child`` in ``parent`` at ``stamp_ns`` (static edges ignore the stamp)."""
        parent, child = self._norm(parent), self._norm(child)
        if not parent or not child or parent == child:
            return
        self.parent[child] = parent
        if static:
            self.static[child] = pose
            self._times.pop(child, None)
            self._poses.pop(child, None)
        else:
            self._times.setdefault(child, []).append(stamp_ns)
            self._poses.setdefault(child, []).append(pose)
            self._sorted = False

    def forget_before(self, stamp_ns: int) -> None:
        """Drop each dynamic link's samples older than ``stamp_ns`` but the last one before it: a live stream's tree
        stays bounded, and a lookup at or after ``stamp_ns`` interpolates as before."""
        if not self._sorted:
            self._sort()
        for child, times in self._times.items():
            i = bisect.bisect_left(times, stamp_ns) - 1
            if i > 0:
                del times[:i], self._poses[child][:i]

    def _sort(self) -> None:
        for child, times in self._times.items():
            order = sorted(range(len(times)), key=times.__getitem__)
            self._times[child] = [times[i] for i in order]
            self._poses[child] = [self._poses[child][i] for i in order]
        self._sorted = True

    def __contains__(self, frame: str) -> bool:
        frame = self._norm(frame)
        return frame in self.parent or frame in self.parent.values()

    def root(self, frame: str) -> str:
        frame = self._norm(frame)
        seen = {frame}
        while frame in self.parent:
            frame = self.parent[frame]
            if frame in seen:
                raise ValueError(f"TF cycle through {frame!r}")
            seen.add(frame)
        return frame

    def edge(self, child: str, stamp_ns: int) -> EgoPose:
        if child in self.static:
            return self.static[child]
        if not self._sorted:
            self._sort()
        return interpolate_pose(self._times[child], self._poses[child], stamp_ns)

    def _chain(self, frame: str, target: str | None) -> list[str]:
        """The frames from ``frame`` up to ``target`` (excluded; None: the root), ``frame`` first. Raises
        ``KeyError`` when ``target`` is not above ``frame`` or the links above it form a cycle."""
        chain: list[str] = []
        cur = frame
        while cur != target and cur in self.parent:
            chain.append(cur)
            cur = self.parent[cur]
            if len(chain) > 1000:
                raise KeyError(f"TF cycle above {frame!r}")
        if target is not None and cur != target:
            raise KeyError(f"frame {target!r} is not above {frame!r} in the TF tree")
        return chain

    def chain(self, frame: str) -> list[str]:
        """The frames from ``frame`` up to its root (excluded), ``frame`` first: each one's link to its parent."""
        return self._chain(self._norm(frame), None)

    def _compose(self, chain: list[str], stamp_ns: int) -> EgoPose:
        pose = IDENTITY
        for child in reversed(chain):
            pose = compose(pose, self.edge(child, stamp_ns))
        return pose

    def lookup(self, frame: str, stamp_ns: int, ancestor: str | None = None) -> EgoPose:
        """Pose of ``frame`` in ``ancestor`` (default: the root of its tree) at ``stamp_ns``.

        Raises ``KeyError`` naming the frames when ``frame`` is unknown or ``ancestor`` is not above it."""
        frame = self._norm(frame)
        if frame not in self:
            raise KeyError(f"frame {frame!r} is not in the TF tree")
        return self._compose(self._chain(frame, self._norm(ancestor) if ancestor else None), stamp_ns)

    def newest(self, frame: str) -> int | None:
        """The latest stamp ``frame`` can be looked up at without clamping: the oldest of the newest samples of the
        dynamic links from it up to its root (None: every link static). Raises ``KeyError`` for an unknown frame."""
        span = self.span(frame)
        return None if span is None else span[1]

    def span(self, frame: str) -> tuple[int, int] | None:
        """The stamps ``frame`` can be looked up at without clamping, first and last: from the newest of the first
        samples of the dynamic links from it up to its root to the oldest of their last ones (None: every link
        static). Raises ``KeyError`` for an unknown frame."""
        frame = self._norm(frame)
        if frame not in self:
            raise KeyError(f"frame {frame!r} is not in the TF tree")
        dynamic = [self._times[c] for c in self._chain(frame, None) if c not in self.static]
        if not dynamic:
            return None
        return max(min(t) for t in dynamic), min(max(t) for t in dynamic)

    def static_lookup(self, frame: str, ancestor: str) -> EgoPose:
        """Pose of ``frame`` in ``ancestor`` composed of static links alone (a sensor's mount).

        Raises ``KeyError`` when ``ancestor`` is not above ``frame`` (or is ``frame`` itself), ``ValueError``
        naming the first link between them that is dynamic."""
        frame, target = self._norm(frame), self._norm(ancestor)
        chain = self._chain(frame, target)
        if not chain:
            raise KeyError(f"frame {target!r} is not above {frame!r} in the TF tree")
        dynamic = [c for c in chain if c not in self.static]
        if dynamic:
            raise ValueError(f"the link {self.parent[dynamic[0]]!r} -> {dynamic[0]!r} is not static")
        return self._compose(chain, 0)  # every link static: the stamp is not read
