"""The detector network, targets, losses and decoding on tiny inputs (issue #6, item 6)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from jitterguard.services.detector.config import LITE, PAPER, Sample
from jitterguard.services.detector.decode import circle_nms, decode
from jitterguard.services.detector.evaluate import Recalibration
from jitterguard.services.detector.inference import Detector, WeightsError, load_weights, save_weights
from jitterguard.services.detector.losses import (centerpoint_loss, distillation_loss, gaussian_focal_loss,
                                                   gaussian_nll)
from jitterguard.services.detector.network import CenterPointNet
from jitterguard.services.detector.pillars import NUM_PILLAR_FEATURES, voxelize
from jitterguard.services.detector.targets import build_targets, gaussian_radius
from jitterguard.services.detector.train import TrainConfig, collate, train

TINY = LITE.model_copy(update=dict(
    name="tiny", point_cloud_range=(-12.8, -12.8, -3.0, 12.8, 12.8, 3.0), voxel_size=(0.2, 0.2, 6.0),
    pfn_channels=8, backbone_layers=(1, 1, 1), backbone_channels=(8, 16, 16), neck_channels=(8, 8, 8),
    head_channels=8, max_pillars=4000,
))
"""128×128 pillars, 32×32 output cells of 0.8 m: big enough for boxes, small enough for a unit test."""


@pytest.fixture(autouse=True)
def _one_thread() -> None:
    torch.set_num_threads(1)


def _box_points(rng: np.random.Generator, box: np.ndarray, n: int) -> np.ndarray:
    """``n`` points on the surface of a box (x, y, z, l, w, h, yaw), with intensity."""
    x, y, z, l, w, h, yaw = box[:7]
    u = rng.uniform(-0.5, 0.5, (n, 3)) * np.array([l, w, h])
    side = rng.integers(0, 2, n)
    u[side == 0, 0] = np.sign(u[side == 0, 0]) * l / 2
    u[side == 1, 1] = np.sign(u[side == 1, 1]) * w / 2
    c, s = math.cos(yaw), math.sin(yaw)
    px = x + c * u[:, 0] - s * u[:, 1]
    py = y + s * u[:, 0] + c * u[:, 1]
    return np.stack([px, py, z + u[:, 2], rng.uniform(0, 255, n)], axis=1).astype(np.float32)


def _scene(seed: int) -> Sample:
    rng = np.random.default_rng(seed)
    boxes = np.array([[4.0, 3.0, -1.0, 4.5, 1.9, 1.6, 0.4, 2.0, 0.0],
                      [-6.0, -5.0, -1.0, 4.3, 1.8, 1.5, -1.2, 0.0, 0.0],
                      [2.0, -8.0, -0.9, 0.7, 0.7, 1.75, 0.0, 0.0, 1.2]], np.float32)
    labels = np.array([0, 0, 4])
    ground = np.stack([rng.uniform(-12.8, 12.8, 3000), rng.uniform(-12.8, 12.8, 3000),
                       np.full(3000, -1.84), rng.uniform(0, 30, 3000)], axis=1).astype(np.float32)
    pts = np.concatenate([ground] + [_box_points(rng, b, 200 if lab == 0 else 60) for b, lab in zip(boxes, labels)])
    return Sample(pts, boxes, labels, np.array([200, 200, 60]), f"tiny/{seed}")


def test_voxelize_groups_points_by_cell_and_caps_each_pillar() -> None:
    pts = torch.tensor([[0.05, 0.05, 0.0, 255.0]] * 30 + [[1.05, 0.05, 0.0, 0.0], [50.0, 0.0, 0.0, 0.0]])
    p = voxelize([pts], TINY)
    assert p.num_points.tolist() == [TINY.max_points_per_pillar, 1]  # out-of-range point dropped, cap applied
    assert len(p.points) == TINY.max_points_per_pillar + 1
    nx, ny = TINY.grid_size
    assert p.coords[:, 1:].tolist() == [[ny // 2, nx // 2], [ny // 2, nx // 2 + 5]]
    assert float(p.points[0, 3]) == pytest.approx(1.0)  # intensity scaled to [0, 1]


def test_a_model_without_intensity_sees_zero_from_every_sensor() -> None:
    """``use_intensity: false`` feeds 0 in the intensity slot whatever the scan carries, so the network's output
    cannot depend on it; the caller's points are not written."""
    rng = np.random.default_rng(3)
    pts = torch.from_numpy(np.concatenate([rng.uniform(-20, 20, (400, 2)), rng.uniform(-1, 1, (400, 1)),
                                           rng.uniform(0, 255, (400, 1))], axis=1).astype(np.float32))
    before = pts.clone()
    blind = TINY.model_copy(update={"use_intensity": False})
    assert float(voxelize([pts], blind).points[:, 3].abs().max()) == 0.0
    assert float(voxelize([pts], TINY).points[:, 3].max()) > 0.5  # the default still feeds it
    assert torch.equal(pts, before)
    torch.manual_seed(0)
    net, bright = CenterPointNet(blind).eval(), pts.clone()
    bright[:, 3] = 255.0 - bright[:, 3]
    with torch.inference_mode():
        a, b = net([pts]), net([bright])
    assert all(torch.equal(a[k], b[k]) for k in a)


def test_voxelize_keeps_the_most_populated_pillars_when_over_budget() -> None:
    cfg = TINY.model_copy(update={"max_pillars": 2})
    pts = torch.tensor([[0.05, 0.05, 0, 0]] * 3 + [[1.05, 0.05, 0, 0]] + [[2.05, 0.05, 0, 0]] * 2, dtype=torch.float32)
    p = voxelize([pts], cfg)
    assert sorted(p.num_points.tolist()) == [2, 3]


def test_a_batch_voxelizes_as_its_scans_one_by_one() -> None:
    """The batch is grouped in one pass; that must equal voxelising each scan alone and concatenating (scans in
    order, pillar indices offset, the pillar budget applied per scan), with an empty scan, out-of-range and
    non-finite points and a budget that cuts some scans and not others."""
    rng = np.random.default_rng(11)

    def scan(n: int, spread: float) -> torch.Tensor:
        xyz = rng.normal(0.0, spread, (n, 3)) * np.array([1.0, 1.0, 0.3])
        pts = np.concatenate([xyz, rng.uniform(0, 255, (n, 1))], axis=1).astype(np.float32)
        pts[::97, 2] = np.nan
        return torch.from_numpy(pts)

    scans = [scan(3000, 8.0), torch.zeros((0, 4)), scan(200, 3.0), scan(5000, 20.0)]
    cfg = TINY.model_copy(update={"max_pillars": 600})
    whole = voxelize(scans, cfg)
    parts = [voxelize([s], cfg) for s in scans]
    assert [len(p.num_points) for p in parts][:3] == [600, 0, len(parts[2].num_points)] and len(parts[2].num_points) < 600
    offsets = np.cumsum([0] + [len(p.num_points) for p in parts[:-1]])
    assert torch.equal(whole.points, torch.cat([p.points for p in parts]))
    assert torch.equal(whole.pillar, torch.cat([p.pillar + int(o) for p, o in zip(parts, offsets)]))
    assert torch.equal(whole.num_points, torch.cat([p.num_points for p in parts]))
    coords = [p.coords.clone() for p in parts]
    for b, c in enumerate(coords):
        c[:, 0] = b
    assert torch.equal(whole.coords, torch.cat(coords)) and whole.batch_size == 4


def test_pillar_features_are_the_nine_of_pointpillars() -> None:
    net = CenterPointNet(TINY)
    pts = torch.tensor([[0.1, 0.1, 0.0, 0.0], [0.15, 0.05, 0.2, 0.0]])
    p = voxelize([pts], TINY)
    f = net.pfn.point_features(p)
    assert f.shape == (2, NUM_PILLAR_FEATURES)
    # offsets to the pillar mean sum to zero; offsets to the pillar centre (0.1, 0.1)
    assert torch.allclose(f[:, 4:7].sum(0), torch.zeros(3), atol=1e-6)
    assert torch.allclose(f[:, 7:9], pts[:, :2] - 0.1, atol=1e-6)


@pytest.mark.parametrize("uncertainty", [True, False])
def test_output_shapes(uncertainty: bool) -> None:
    cfg = TINY.model_copy(update={"uncertainty": uncertainty})
    out = CenterPointNet(cfg)([torch.from_numpy(_scene(0).points)] * 2)
    w, h = cfg.feature_map_size
    assert out["heatmap"].shape == (2, 5, h, w)
    assert out["reg"].shape == (2, 2, h, w) and out["dim"].shape == (2, 3, h, w) and out["vel"].shape == (2, 2, h, w)
    assert ("logvar" in out) is uncertainty
    if uncertainty:
        assert out["logvar"].shape == (2, 5, h, w)


def test_paper_preset_matches_design() -> None:
    assert PAPER.grid_size == (512, 512)
    assert PAPER.backbone_layers == (3, 5, 5) and PAPER.backbone_channels == (64, 128, 256)
    assert sum(PAPER.neck_channels) == 384
    net = CenterPointNet(PAPER)
    assert net.head.shared[0].in_channels == 384


def test_focal_loss_values() -> None:
    target = torch.zeros(1, 1, 3, 3)
    target[0, 0, 1, 1] = 1.0
    logits = torch.full((1, 1, 3, 3), -20.0)
    logits[0, 0, 1, 1] = 20.0
    assert float(gaussian_focal_loss(logits, target)) < 1e-6  # near-perfect prediction
    p = 0.5
    logits = torch.zeros(1, 1, 3, 3)
    # positive: -log(p)(1-p)^2; 8 negatives with gt 0: -log(1-p) p^2
    expected = -(math.log(p) * (1 - p) ** 2 + 8 * math.log(1 - p) * p ** 2)
    assert float(gaussian_focal_loss(logits, target)) == pytest.approx(expected, rel=1e-3)


def test_gaussian_nll_value_and_clamp() -> None:
    mean, target = torch.tensor([1.0]), torch.tensor([0.0])
    s = torch.tensor([math.log(4.0)])
    assert float(gaussian_nll(mean, target, s)) == pytest.approx(0.5 / 4.0 + 0.5 * math.log(4.0))
    low = torch.tensor([-30.0], requires_grad=True)
    v = gaussian_nll(mean, target, low)
    assert float(v.detach()) == pytest.approx(0.5 * math.exp(10.0) - 5.0)  # clamped at -10
    v.backward()
    assert float(low.grad) == 0.0  # below the clamp no gradient


def test_nll_gradient_on_the_mean_shrinks_as_predicted_variance_grows() -> None:
    grads = []
    for logvar in (-4.0, 0.0, 4.0):
        mean = torch.tensor([1.0], requires_grad=True)
        gaussian_nll(mean, torch.tensor([0.0]), torch.tensor([logvar])).backward()
        grads.append(abs(float(mean.grad)))
    assert grads[0] > grads[1] > grads[2] > 0


def test_gaussian_radius_grows_with_box_size() -> None:
    assert gaussian_radius(2.0, 2.0, 0.1) < gaussian_radius(6.0, 3.0, 0.1)
    assert gaussian_radius(6.0, 3.0, 0.7) < gaussian_radius(6.0, 3.0, 0.1)


def _perfect_maps(t, cfg, uncertainty: bool) -> dict[str, torch.Tensor]:
    """Head maps that reproduce targets ``t`` exactly (logits ±20 from the heatmap)."""
    w, h = cfg.feature_map_size
    hm = torch.from_numpy(t.heatmap)[None]
    logits = torch.where(hm >= 1.0, torch.tensor(20.0), torch.tensor(-20.0))
    maps = {"heatmap": logits}
    chans = {"reg": (0, 2), "height": (2, 3), "dim": (3, 6), "rot": (6, 8), "vel": (8, 10)}
    for name, (a, b) in chans.items():
        m = torch.zeros(1, b - a, h * w)
        for k in np.flatnonzero(t.mask):
            m[0, :, t.ind[k]] = torch.from_numpy(t.box[k, a:b])
        maps[name] = m.view(1, b - a, h, w)
    if uncertainty:
        maps["logvar"] = torch.full((1, 5, h, w), math.log(0.01))
    return maps


def test_targets_decode_back_to_the_boxes() -> None:
    s = _scene(1)
    t = build_targets(s, TINY)
    assert t.mask.sum() == 3 and t.heatmap.max() == 1.0
    dets = decode(_perfect_maps(t, TINY, True), TINY)[0]
    assert len(dets) == 3
    order = np.argsort(dets.boxes[:, 0])
    want = s.boxes[np.argsort(s.boxes[:, 0])]
    np.testing.assert_allclose(dets.boxes[order], want, atol=1e-4)
    assert sorted(dets.labels.tolist()) == [0, 0, 4]
    np.testing.assert_allclose(dets.log_variances, math.log(0.01), atol=1e-6)


def test_targets_skip_unseen_and_out_of_range_boxes() -> None:
    s = _scene(2)
    boxes = np.concatenate([s.boxes, [[30.0, 0, -1, 4, 2, 1.5, 0, 0, 0]]]).astype(np.float32)
    s2 = Sample(s.points, boxes, np.append(s.labels, 0), np.array([200, 0, 60, 50]))
    t = build_targets(s2, TINY)
    assert t.mask.sum() == 2  # the 0-point car and the out-of-range car are not targets


def test_perfect_maps_have_lower_loss_than_random_ones() -> None:
    s = _scene(3)
    t = build_targets(s, TINY)
    batch = collate([(torch.from_numpy(s.points), {"heatmap": t.heatmap, "ind": t.ind, "mask": t.mask,
                                                   "box": t.box, "yaw": t.yaw})])[1]
    good = centerpoint_loss(_perfect_maps(t, TINY, True), batch, TINY)
    torch.manual_seed(0)
    rnd = centerpoint_loss(CenterPointNet(TINY)([torch.from_numpy(s.points)]), batch, TINY)
    assert float(good["heatmap"].detach()) < 0.01 < float(rnd["heatmap"].detach())
    assert float(good["shape"].detach()) < 1e-5 < float(rnd["shape"].detach())
    assert float(good["loss"].detach()) < float(rnd["loss"].detach())


def test_circle_nms_suppresses_close_lower_scores_only() -> None:
    xy = np.array([[0, 0], [0.5, 0], [3, 0], [3.1, 0]], np.float32)
    keep = circle_nms(xy, np.array([0.9, 0.8, 0.5, 0.7], np.float32), dist2=1.0)
    assert keep.tolist() == [0, 3]


def test_short_training_lowers_the_loss(tmp_path) -> None:
    samples = [_scene(i) for i in range(4)]
    torch.manual_seed(0)
    model = CenterPointNet(TINY)
    state = train(model, samples, [], TrainConfig(epochs=8, batch_size=2, lr=5e-3, seed=0), tmp_path,
                  progress=False)
    losses = [h["loss"] for h in state.history]
    assert losses[-1] < 0.5 * losses[0]
    assert (tmp_path / "weights.pt").is_file() and (tmp_path / "checkpoint.pt").is_file()


def test_distillation_loss_is_the_kl_of_the_named_channels_only() -> None:
    """Zero where the student's heatmap equals the teacher's; the Bernoulli KL of the named channels, cell by cell,
    over the object count otherwise; blind to every other channel."""
    g = torch.Generator().manual_seed(0)
    teacher = torch.randn(2, 5, 4, 4, generator=g)
    assert float(distillation_loss(teacher.clone(), teacher, (4,), 3.0)) == pytest.approx(0.0, abs=1e-6)
    student = teacher.clone()
    student[:, 0] += 3.0  # a class not held: no cost
    assert float(distillation_loss(student, teacher, (4,), 3.0)) == pytest.approx(0.0, abs=1e-6)
    student[:, 4] -= 1.0
    p, q = torch.sigmoid(student[:, 4]), torch.sigmoid(teacher[:, 4])
    kl = (q * torch.log(q / p) + (1 - q) * torch.log((1 - q) / (1 - p))).sum() / 3.0
    assert float(distillation_loss(student, teacher, (4,), 3.0)) == pytest.approx(float(kl), rel=1e-4)
    assert float(distillation_loss(student, teacher, (0, 4), 3.0)) > float(kl)


def test_a_distilled_fine_tune_keeps_the_teachers_heatmap_of_the_held_class(tmp_path) -> None:
    """Fine-tuning on scenes without pedestrians teaches the network to call the pedestrian cell empty; held to
    its teacher's pedestrian heatmap it stays nearer what the teacher says there than the same run without."""
    torch.manual_seed(0)
    teacher = CenterPointNet(TINY)
    train(teacher, [_scene(i) for i in range(4)], [], TrainConfig(epochs=6, batch_size=2, lr=5e-3, seed=0),
          tmp_path / "t", progress=False)
    no_peds = []
    for i in range(4, 8):
        s = _scene(i)
        no_peds.append(Sample(s.points, s.boxes[:2], s.labels[:2], s.num_points[:2], s.token))
    ped = TINY.class_names.index("pedestrian")
    probe = [_scene(i) for i in range(8, 10)]

    def drift(channels: tuple[int, ...]) -> float:
        student = CenterPointNet(TINY)
        student.load_state_dict(teacher.state_dict())
        cfg = TrainConfig(epochs=4, batch_size=2, lr=5e-3, seed=1, distill_channels=channels, distill_weight=5.0)
        train(student, no_peds, [], cfg, tmp_path / f"s{channels}", progress=False, teacher=teacher,
              write_weights=False)
        student.eval(), teacher.eval()
        with torch.no_grad():
            pts = [torch.from_numpy(s.points) for s in probe]
            return float(distillation_loss(student(pts)["heatmap"], teacher(pts)["heatmap"], (ped,)))

    held, free = drift((ped,)), drift(())
    assert held < 0.5 * free
    with pytest.raises(ValueError, match="teacher"):
        train(CenterPointNet(TINY), no_peds, [], TrainConfig(epochs=1, distill_channels=(ped,)), tmp_path / "x",
              progress=False)


def test_resume_reproduces_the_uninterrupted_run(tmp_path) -> None:
    samples = [_scene(i) for i in range(4)]
    cfg = TrainConfig(epochs=3, batch_size=2, lr=5e-3, seed=1)
    torch.manual_seed(0)
    full = CenterPointNet(TINY)
    train(full, samples, [], cfg, tmp_path / "full", progress=False)
    torch.manual_seed(0)
    part = CenterPointNet(TINY)
    state = train(part, samples, [], cfg, tmp_path / "run", progress=False, stop_after=2)
    assert state.epoch == 2 and not (tmp_path / "run" / "weights.pt").exists()
    torch.manual_seed(123)  # a different init: resume must overwrite it from the checkpoint
    resumed = CenterPointNet(TINY)
    state = train(resumed, samples, [], cfg, tmp_path / "run", resume=True, progress=False)
    assert state.epoch == 3 and len(state.history) == 3
    for (name, a), b in zip(full.state_dict().items(), resumed.state_dict().values()):
        assert torch.allclose(a.float(), b.float(), atol=1e-5), name


def test_weights_round_trip_and_reject_bad_files(tmp_path) -> None:
    torch.manual_seed(0)
    model = CenterPointNet(TINY).eval()
    path = tmp_path / "w.pt"
    save_weights(path, model, recalibration=(2.0, 0.5), meta={"note": "test"})
    loaded, rec, meta = load_weights(path)
    assert rec == Recalibration(((2.0, 0.5),)) and meta["note"] == "test" and loaded.config == TINY
    binned = Recalibration(((3.0, 2.0), (1.0, 0.5)), (0.5,))
    save_weights(tmp_path / "b.pt", model, recalibration=binned)
    assert load_weights(tmp_path / "b.pt")[1] == binned  # score bins survive the weights-only round trip
    pts = _scene(4).points
    a = Detector(model).detect(pts)
    b = Detector(loaded).detect(pts)
    np.testing.assert_array_equal(a.boxes, b.boxes)
    c = Detector(loaded, recalibration=rec).detect(pts)
    np.testing.assert_allclose(c.log_variances[:, 0], a.log_variances[:, 0] + math.log(2.0), atol=1e-5)
    (tmp_path / "bad.pt").write_bytes(b"not a torch file")
    with pytest.raises(WeightsError):
        load_weights(tmp_path / "bad.pt")
    torch.save({"format": 1, "config": {"nope": 1}, "state_dict": {}}, str(tmp_path / "cfg.pt"))
    with pytest.raises(WeightsError, match="unknown fields"):
        load_weights(tmp_path / "cfg.pt")
    bad = torch.load(str(path), weights_only=True)
    bad["recalibration"] = {"scales": [[1.0, 1.0], [1.0, 1.0]], "score_edges": []}
    torch.save(bad, str(tmp_path / "rec.pt"))
    with pytest.raises(WeightsError, match="recalibration"):
        load_weights(tmp_path / "rec.pt")
    # a dict of the right format whose entries are not what they must be: WeightsError (one line in every CLI),
    # not the KeyError / TypeError / ValueError traceback they had been
    good = torch.load(str(path), weights_only=True)
    for key, value in (("config", None), ("state_dict", 5), ("meta", "abc"), ("meta", [1, 2])):
        broken = {**good, key: value} if value is not None else {k: v for k, v in good.items() if k != key}
        torch.save(broken, str(tmp_path / "broken.pt"))
        with pytest.raises(WeightsError, match=f"its '{key}' is"):
            load_weights(tmp_path / "broken.pt")
    torch.save({**good, "meta": None}, str(tmp_path / "nometa.pt"))
    assert load_weights(tmp_path / "nometa.pt")[2] == {}

