"""Synthetic world with ground truth, a ray-cast LiDAR, and a detection-level noise model.

Pure library code (no I/O outside :mod:`jitterguard.sim.export`, :mod:`jitterguard.sim.bev` and the CLI).
"""

from .detection_model import DetectionFrame, DetectionModel, NoiseConfig
from .world import SCENARIO_NAMES, SENSOR_HEIGHT_M, GroundTruthFrame, Scenario, make_scenario

__all__ = [
    "DetectionFrame",
    "DetectionModel",
    "GroundTruthFrame",
    "NoiseConfig",
    "SCENARIO_NAMES",
    "SENSOR_HEIGHT_M",
    "Scenario",
    "make_scenario",
]
