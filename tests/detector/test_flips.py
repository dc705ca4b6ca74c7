"""Test-time flips (``flips``): the mirror images' outputs land back on the scan's own grid with the right signs,
and a detector that averages them answers a mirrored scan with the mirrored detections."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from jitterguard.services.detector.config import PRESETS
from jitterguard.services.detector.data import synthetic_samples
from jitterguard.services.detector.decode import decode
from jitterguard.services.detector.flips import MIRRORS, check_symmetric, merge_mirrored
from jitterguard.services.detector.inference import Detector
from jitterguard.services.detector.network import HEAD_CHANNELS

LITE = PRESETS["lite"]


def _maps_with_one_object(x: float, y: float, yaw: float, vx: float, vy: float, prob: float) -> dict[str, torch.Tensor]:
    """Head maps (batch 1) that decode to one car at (x, y) with heading ``yaw`` and velocity (vx, vy), encoded
    the way :func:`~jitterguard.services.detector.decode.decode` reads them — written out here, independently of
    the module under test."""
    h, w = LITE.feature_map_size[1], LITE.feature_map_size[0]
    r = LITE.point_cloud_range
    cell = LITE.voxel_size[0] * LITE.out_size_factor
    fx, fy = (x - r[0]) / cell, (y - r[1]) / cell
    ix, iy = int(math.floor(fx)), int(math.floor(fy))
    maps = {"heatmap": torch.full((1, LITE.num_classes, h, w), -20.0)}
    maps.update({name: torch.zeros(1, c, h, w) for name, c in HEAD_CHANNELS.items()})
    maps["logvar"] = torch.full((1, 5, h, w), -3.0)
    maps["heatmap"][0, 0, iy, ix] = math.log(prob / (1 - prob))
    maps["reg"][0, :, iy, ix] = torch.tensor([fx - ix, fy - iy])
    maps["height"][0, 0, iy, ix] = -0.9
    maps["dim"][0, :, iy, ix] = torch.tensor([math.log(4.5), math.log(1.9), math.log(1.6)])
    maps["rot"][0, :, iy, ix] = torch.tensor([math.sin(yaw), math.cos(yaw)])
    maps["vel"][0, :, iy, ix] = torch.tensor([vx, vy])
    return maps


def _mirrored(box: tuple[float, float, float, float, float], mx: bool, my: bool) -> tuple[float, ...]:
    """(x, y, yaw, vx, vy) as seen in the mirror image: x → −x turns yaw into π − yaw, y → −y into −yaw."""
    x, y, yaw, vx, vy = box
    if mx:
        x, yaw, vx = -x, math.pi - yaw, -vx
    if my:
        y, yaw, vy = -y, -yaw, -vy
    return x, y, yaw, vx, vy


def _batch(views: list[dict[str, torch.Tensor]]) -> dict[str, torch.Tensor]:
    return {k: torch.cat([v[k] for v in views]) for k in views[0]}


@pytest.mark.parametrize("box", [(12.3, -7.9, 0.4, 3.0, -1.2), (-30.05, 21.7, 2.9, -8.0, 0.5),
                                 (0.7, 0.3, -1.7, 0.0, 4.0)])
def test_each_mirror_image_of_an_object_merges_back_onto_the_object(box: tuple[float, ...]) -> None:
    """Four views that each see the object as its mirror image shows it decode, once merged, to the object
    itself: position, heading and velocity — so every sign and cell rule of the merge is right."""
    views = [_maps_with_one_object(*_mirrored(box, mx, my), prob=0.8) for mx, my in MIRRORS]
    (det,) = decode(merge_mirrored(_batch(views)), LITE, score_threshold=0.1)
    assert len(det) == 1
    x, y, yaw, vx, vy = box
    b = det.boxes[0]
    assert b[0] == pytest.approx(x, abs=1e-4) and b[1] == pytest.approx(y, abs=1e-4)
    assert math.cos(b[6] - yaw) == pytest.approx(1.0, abs=1e-6)
    assert b[7] == pytest.approx(vx, abs=1e-5) and b[8] == pytest.approx(vy, abs=1e-5)
    assert det.scores[0] == pytest.approx(0.8, abs=1e-4)


def test_a_peak_seen_in_one_view_only_keeps_a_quarter_of_its_probability() -> None:
    seen = _maps_with_one_object(12.3, -7.9, 0.4, 0.0, 0.0, prob=0.8)
    unseen = _maps_with_one_object(12.3, -7.9, 0.4, 0.0, 0.0, prob=1e-6)
    (det,) = decode(merge_mirrored(_batch([seen, unseen, unseen, unseen])), LITE, score_threshold=0.1)
    assert len(det) == 1 and det.scores[0] == pytest.approx(0.2, abs=1e-4)  # (0.8 + 3 · ~0) / 4


def test_flips_refuse_a_grid_that_is_not_symmetric_about_the_sensor() -> None:
    check_symmetric(LITE)  # the shipped grids are
    check_symmetric(PRESETS["paper"])
    shifted = LITE.model_copy(update={"point_cloud_range": (-40.0, -51.2, -3.0, 62.4, 51.2, 3.0)})
    with pytest.raises(ValueError, match="symmetric"):
        check_symmetric(shifted)


@pytest.fixture(scope="module")
def scan() -> np.ndarray:
    (sample,) = synthetic_samples(["parking-street"], [1000], frames_per_scenario=1)
    return sample.points


def test_the_averaged_detector_answers_a_mirrored_scan_with_the_mirrored_detections(scan: np.ndarray) -> None:
    """The four views of a scan and of its mirror image are the same four scans, so a correct merge makes the
    detector exactly mirror-equivariant — which a single pass of the network is not."""
    flipped = Detector.load(None, "lite", threads=2, flips=True)
    single = Detector.load(None, "lite", threads=2)
    mirror = scan.copy()
    mirror[:, 0] = -mirror[:, 0]

    def cars(det) -> np.ndarray:  # noqa: ANN001 - (x, y, cos yaw, sin yaw, vx, vy, score) of confident cars
        k = (det.labels == 0) & (det.scores > 0.3)
        b = det.boxes[k]
        return np.column_stack([b[:, 0], b[:, 1], np.cos(b[:, 6]), np.sin(b[:, 6]), b[:, 7], b[:, 8], det.scores[k]])

    def mirrored(c: np.ndarray) -> np.ndarray:
        m = c.copy()
        m[:, 0], m[:, 2], m[:, 4] = -c[:, 0], -c[:, 2], -c[:, 4]  # x, cos yaw (yaw → π − yaw), vx
        return m

    def sorted_rows(c: np.ndarray) -> np.ndarray:
        return c[np.lexsort((c[:, 1], c[:, 0]))]

    a, b = cars(flipped.detect(scan)), cars(flipped.detect(mirror))
    assert len(a) >= 3 and a.shape == b.shape
    np.testing.assert_allclose(sorted_rows(mirrored(a)), sorted_rows(b), atol=2e-3)
    s_a, s_b = cars(single.detect(scan)), cars(single.detect(mirror))
    if s_a.shape == s_b.shape:  # a single pass sees a mirrored scan as another scan
        assert not np.allclose(sorted_rows(mirrored(s_a)), sorted_rows(s_b), atol=2e-3)


@pytest.mark.parametrize("argv", [
    ["eval-detector", "--out", "{out}", "--weights", "{w}", "--flips", "--nuscenes", "{out}"],
    ["eval", "--scenario", "mixed", "--input", "detector", "--weights", "{w}", "--detector-flips", "--out", "{out}"],
    ["adapt", "--weights", "{w}", "--out", "{out}", "--scans", "{out}", "--flips"],
    ["detector", "--weights", "{w}", "--flips"],  # the service: refused before it opens a session
    ["bench", "detector", "--json", "--presets", "lite", "--backends", "torch", "--weights", "lite={w}", "--scans",
     "1", "--warmup", "0", "--flips", "--no-progress"],
])
def test_flips_on_weights_with_an_off_centre_grid_are_one_line_and_exit_2(tmp_path, argv: list[str]) -> None:  # noqa: ANN001
    import subprocess
    import sys

    from jitterguard.services.detector.inference import save_weights
    from jitterguard.services.detector.network import CenterPointNet

    shifted = LITE.model_copy(update={"point_cloud_range": (-40.0, -51.2, -3.0, 62.4, 51.2, 3.0)})
    w = tmp_path / "shifted.pt"
    save_weights(w, CenterPointNet(shifted))
    args = [a.format(out=tmp_path, w=w) for a in argv]
    res = subprocess.run([sys.executable, "-m", "jitterguard.cli", *args], capture_output=True, text=True, timeout=300)
    assert res.returncode == 2, res.stderr[-2000:]
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and "flips" in lines[0] and "symmetric" in lines[0], lines
