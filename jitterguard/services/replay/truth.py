"""Ground truth on the wire: a source's labels as ``GroundTruthObjects`` for ``jg/{ns}/groundtruth``.

Only viewers and recorders subscribe to that key (the Foxglove bridge draws it); nothing in the pipeline does, so
no label of a replayed scene can reach the tracker or the classifier.
"""

from __future__ import annotations

from typing import Any

from ...geometry import quaternion_from_yaw
from ...schemas.models import GroundTruthObjects


def truth_message(gt: Any) -> GroundTruthObjects:
    """A ground-truth frame (synthetic or nuScenes, :class:`jitterguard.sim.world.GroundTruthFrame`) as the wire's
    ``GroundTruthObjects`` (world frame; the publisher sets the header's seq and stamp). ``moving`` is the
    evaluator's motion truth (:func:`jitterguard.eval.groundtruth.is_dynamic`)."""
    from ...eval.groundtruth import is_dynamic  # the evaluator's area: imported when a source has labels

    objs = []
    for k in range(gt.num_objects):
        x, y, z = (float(v) for v in gt.centers[k])
        q = quaternion_from_yaw(float(gt.yaws[k]))
        objs.append({
            "instance_id": str(int(gt.instance_ids[k])), "label": int(gt.labels[k]),
            "pose": {"position": {"x": x, "y": y, "z": z}, "orientation": dict(zip("xyzw", q, strict=True))},
            "dimensions": dict(zip("xyz", (float(v) for v in gt.sizes[k]), strict=True)),
            "velocity": {"x": float(gt.velocities[k][0]), "y": float(gt.velocities[k][1]), "z": 0.0},
            "moving": is_dynamic(gt.attributes[k], bool(gt.moving[k])), "attribute": gt.attributes[k],
        })
    return GroundTruthObjects.model_validate({"header": {"stamp": int(gt.stamp_ns), "frame_id": "map",
                                                         "seq": int(gt.seq)}, "objects": objs})
