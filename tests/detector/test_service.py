"""The detector service over real in-process Zenoh (peer mode, loopback, multicast off, free ports).

The network is the real lite CenterPoint, randomly initialised (its detections are meaningless but it produces
hundreds above a low threshold), on real ray-cast HDL-32E scans from the synthetic world. What is tested is the
wiring: header and ego pose carried over, covariance fields filled from the model's variances, newest-scan
dropping with every skipped scan counted and logged, malformed payloads rejected without stopping the service.
"""

from __future__ import annotations

import json
import logging
import os
import signal
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path

import msgpack
import numpy as np
import pytest
import torch
import zenoh

from jitterguard.geometry import quaternion_from_yaw
from jitterguard.runtime import loopback_options
from jitterguard.schemas import DecodeError, decode, encode, keys
from jitterguard.schemas.models import X_X, Y_Y, YAW_YAW, DetectedObjects, Header, Point, PointCloud, Pose, Quaternion
from jitterguard.services.detector.inference import Detector
from jitterguard.services.detector.service import BehindReport, DetectorService
from jitterguard.sim.lidar import cast_frame
from jitterguard.sim.world import make_scenario

from helpers import wait_until

pytestmark = pytest.mark.integration
NS = "dettest"
STAMP0 = 1_700_000_000_000_000_000
TIMEOUT = 60.0  # generous: the machine is shared; nothing here asserts a duration


class GatedDetector(Detector):
    """The real detector behind a gate the test opens: lets a test hold the worker inside ``detect`` so scans
    pile up deterministically, however fast or slow the machine is."""

    gate: threading.Event
    entered: threading.Event

    def detect(self, points: np.ndarray):  # type: ignore[override]
        self.entered.set()
        assert self.gate.wait(TIMEOUT), "test never opened the gate"
        return super().detect(points)


@pytest.fixture(scope="module")
def scans() -> list[tuple[np.ndarray, Pose]]:
    """Two real HDL-32E scans (x, y, z, intensity, ring) with their sensor poses."""
    return _cast((0, 5))


def _cast(frames: tuple[int, ...]) -> list[tuple[np.ndarray, Pose]]:
    """Real HDL-32E scans of these frames of a 10 Hz scenario, with their sensor poses."""
    sc = make_scenario("parking-street", 0, duration_s=2.0, rate_hz=10.0)
    out = []
    for i in frames:
        res, gt = cast_frame(sc.frame(i), seed=0)
        pts = np.column_stack([res.points, res.ring]).astype(np.float32)
        qx, qy, qz, qw = quaternion_from_yaw(float(gt.ego_yaw))
        pose = Pose(position=Point(x=float(gt.ego_x), y=float(gt.ego_y), z=1.84),
                    orientation=Quaternion(x=qx, y=qy, z=qz, w=qw))
        out.append((pts, pose))
    return out


@pytest.fixture(scope="module")
def detector() -> Detector:
    torch.set_num_threads(1)
    det = GatedDetector.load(None, "lite", threads=1, score_threshold=0.05)
    det.gate, det.entered = threading.Event(), threading.Event()
    det.gate.set()
    return det


class Client:
    """Plays replay (publishes ``points``) and tracker (collects ``detections``)."""

    def __init__(self, session: zenoh.Session) -> None:
        self.session = session
        self.lock = threading.Lock()
        self.got: list[DetectedObjects] = []
        self.sub = session.declare_subscriber(keys.detections(NS), self._on)
        self.pub = session.declare_publisher(keys.points(NS), congestion_control=zenoh.CongestionControl.BLOCK)

    def _on(self, s: zenoh.Sample) -> None:
        msg = decode(DetectedObjects, s.payload.to_bytes())
        with self.lock:
            self.got.append(msg)

    def seqs(self) -> list[int]:
        with self.lock:
            return [m.header.seq for m in self.got]

    def send(self, pts: np.ndarray, pose: Pose, seq: int) -> PointCloud:
        msg = PointCloud(header=Header(stamp=STAMP0 + seq * 50_000_000, frame_id="lidar", seq=seq), ego_pose=pose,
                         fields=["x", "y", "z", "intensity", "ring"], num_points=len(pts),
                         data=pts.astype("<f4").tobytes())
        self.pub.put(encode(msg))
        return msg


@pytest.fixture
def harness(zenoh_port: int, client_session: zenoh.Session, detector: Detector) -> Iterator[tuple[DetectorService, Client]]:
    detector.gate.set()
    svc = DetectorService(loopback_options(NS, zenoh_port, listen_self=True), detector)
    client = Client(client_session)
    assert wait_until(lambda: client.pub.matching_status.matching, TIMEOUT), "service never subscribed points"
    yield svc, client
    detector.gate.set()
    svc.close()


def test_scan_in_detections_out_with_header_pose_and_variances(harness, scans, detector) -> None:
    svc, client = harness
    pts, pose = scans[0]
    sent = client.send(pts, pose, seq=7)
    assert wait_until(lambda: client.seqs() == [7], TIMEOUT)
    msg = client.got[0]
    assert msg.header == sent.header and msg.ego_pose == pose
    # the same network on the same points, here: the published variances are exp(its log-variances)
    want = detector.detect(pts[:, :4])
    assert len(want) > 0 and len(msg.objects) == len(want)
    var = np.exp(want.log_variances.astype(np.float64))
    for o, v, b in zip(msg.objects, var, want.boxes):
        cov = o.kinematics.pose_with_covariance.covariance
        tcov = o.kinematics.twist_with_covariance.covariance
        assert o.kinematics.has_position_covariance and o.kinematics.has_twist_covariance
        assert (cov[X_X], cov[Y_Y], cov[YAW_YAW], tcov[X_X], tcov[Y_Y]) == pytest.approx(
            (v[0], v[1], v[4], v[2], v[3]), rel=1e-4)
        assert o.kinematics.pose_with_covariance.pose.position.x == pytest.approx(float(b[0]), abs=1e-4)
    c = svc.counters.snapshot()
    assert c["scans"] == 1 and c["detections"] == len(want) and c.get("skipped_scans", 0) == 0
    assert svc.last_seq == 7
    # the height the scan's frame was taken to have, measured from its ground (the synthetic sensor: 1.84 m)
    assert c["sensor_height_cm_last"] == round(detector.ground_last.height * 100) and 174 <= c["sensor_height_cm_last"] <= 194
    assert c["ground_slope_x_cdeg_last"] == round(detector.ground_last.slope_deg[0] * 100)
    assert abs(c["ground_slope_y_cdeg_last"]) < 300  # a synthetic street: within a few degrees of level


def test_flooded_detector_skips_to_the_newest_scan_and_says_so(harness, scans, detector, caplog) -> None:
    svc, client = harness
    n = 8
    detector.gate.clear()
    detector.entered.clear()
    with caplog.at_level(logging.WARNING, logger="jitterguard.detector"):
        client.send(*scans[0], seq=0)
        assert detector.entered.wait(TIMEOUT)  # the worker holds scan 0 inside the network
        for seq in range(1, n):
            client.send(*scans[seq % 2], seq=seq)
        assert wait_until(lambda: svc.counters.get("received") == n, TIMEOUT)
        detector.gate.set()
        assert wait_until(lambda: client.seqs()[-1:] == [n - 1], TIMEOUT)
        # the worker counts a scan after its put, so the output can arrive before the counter moves
        assert wait_until(lambda: svc.counters.get("scans") == 2, TIMEOUT)
    c = svc.counters.snapshot()
    # scan 0 was being processed; 1..6 were each replaced by a newer one before the worker came back
    assert client.seqs() == [0, n - 1]
    assert c["skipped_scans"] == n - 2 and c["scans"] == 2
    assert c["scans"] + c["skipped_scans"] == c["received"]  # every scan accounted for
    assert svc.heartbeat().counters["skipped_scans"] == n - 2
    behind = [r.getMessage() for r in caplog.records if "falling behind" in r.getMessage()]
    assert len(behind) == 1, behind  # one burst, one line
    assert "skipped 6 scan(s) (seqs 1..6)" in behind[0] and "seq 7" in behind[0]


def test_scans_without_a_road_plane_are_told_to_the_operator_once(harness, caplog) -> None:
    """A frame whose z is not up (here: a wall in front of the sensor and nothing below it) gives no road plane;
    after 20 such scans in a row one warning says what the frame must be, and the next ones say nothing more."""
    svc, client = harness
    n = 200
    wall = np.column_stack([np.full(n, 6.0), np.linspace(-10, 10, n), np.linspace(-1, 3, n), np.zeros(n),
                            np.zeros(n)]).astype(np.float32)
    pose = Pose(position=Point(x=0.0, y=0.0, z=0.0), orientation=Quaternion(x=0.0, y=0.0, z=0.0, w=1.0))
    with caplog.at_level(logging.WARNING, logger="jitterguard.detector"):
        for k in range(25):  # one at a time: a scan the busy worker skipped would not be measured
            client.send(wall, pose, seq=300 + k)
            assert wait_until(lambda: 300 + k in client.seqs(), TIMEOUT)
    told = [r.getMessage() for r in caplog.records if "no road plane found" in r.getMessage()]
    assert len(told) == 1 and "x forward and z up" in told[0], told
    assert svc.detector.plane_measured is None


def test_scans_without_intensity_are_counted_and_told_once(harness, scans, caplog) -> None:
    """A cloud of x, y, z only, given to weights trained with intensity: fed 0 as documented (the shipped network
    then finds fewer objects), counted and said once — it had been silent."""
    svc, client = harness
    pts, pose = scans[0]
    with caplog.at_level(logging.WARNING, logger="jitterguard.detector"):
        for seq in (400, 401):
            msg = PointCloud(header=Header(stamp=STAMP0 + seq * 50_000_000, frame_id="lidar", seq=seq), ego_pose=pose,
                             fields=["x", "y", "z"], num_points=len(pts), data=pts[:, :3].astype("<f4").tobytes())
            client.pub.put(encode(msg))
            assert wait_until(lambda: seq in client.seqs(), TIMEOUT)
        client.send(pts, pose, seq=402)  # with intensity: not counted
        assert wait_until(lambda: 402 in client.seqs(), TIMEOUT)
    told = [r.getMessage() for r in caplog.records if "no 'intensity' field" in r.getMessage()]
    assert len(told) == 1 and "--no-intensity" in told[0], told
    assert svc.counters.get("scans_without_intensity") == 2


def test_steady_overload_is_summarised_and_a_new_burst_reported_at_once() -> None:
    rep = BehindReport(quiet_s=5.0, summary_s=30.0)
    assert rep.taken(0.0, seq=0, skipped=0, first=-1, last=-1, detect_ms=90) is None
    first = rep.taken(0.25, seq=3, skipped=2, first=1, last=2, detect_ms=300)
    assert first is not None and "skipped 2 scan(s) (seqs 1..2)" in first and "seq 3" in first
    t, lines = 0.25, []
    for k in range(120):  # a steady overload: every take skips two scans, 0.25 s apart (exact in binary), 30 s
        t += 0.25
        line = rep.taken(t, seq=6 + 3 * k, skipped=2, first=4 + 3 * k, last=5 + 3 * k, detect_ms=300)
        if line:
            lines.append((t, line))
    assert len(lines) == 1  # quiet in between, one summary once 30 s passed
    when, summary = lines[0]
    assert when == 30.25 and "still falling behind" in summary
    assert "skipped 240 scan(s) and processed 120 in the last 30 s" in summary
    assert rep.taken(t + 1.0, seq=400, skipped=0, first=-1, last=-1, detect_ms=80) is None  # caught up
    again = rep.taken(t + 7.0, seq=402, skipped=1, first=401, last=401, detect_ms=300)  # after a quiet gap
    assert again is not None and again.startswith("falling behind: skipped 1 scan(s) (seq 401)")


def test_malformed_payloads_are_rejected_and_the_next_scan_still_runs(harness, scans) -> None:
    svc, client = harness
    client.pub.put(b"\x00 not msgpack")
    bad = msgpack.unpackb(encode(client_cloud(scans[0][0][:10])), raw=False)
    bad["num_points"] = 11  # buffer no longer matches: schema validation must refuse it
    client.pub.put(msgpack.packb(bad, use_bin_type=True))
    assert wait_until(lambda: svc.counters.get("rejected") == 2, TIMEOUT)
    client.send(*scans[1], seq=3)
    assert wait_until(lambda: client.seqs() == [3], TIMEOUT)
    assert wait_until(lambda: svc.counters.get("scans") == 1, TIMEOUT)  # counted just after the put
    c = svc.counters.snapshot()
    assert c["rejected.points"] == 2 and c["scans"] == 1 and c.get("detect_errors", 0) == 0


def test_a_scan_whose_ego_pose_is_no_pose_is_refused_and_counted(harness, scans) -> None:
    """The readers downstream refuse a frame whose ego orientation is no unit quaternion or whose position lies
    beyond the limits: the detector refuses such a scan itself (counted per key), before the network or the sweeps
    see it, rather than publishing a frame the tracker would refuse."""
    svc, client = harness
    pts, pose = scans[0]
    client.send(pts, pose.model_copy(update={"orientation": Quaternion(w=2.0)}), seq=1)
    client.send(pts, pose.model_copy(update={"orientation": Quaternion(w=0.0)}), seq=2)
    client.send(pts, pose.model_copy(update={"position": Point(x=2e7)}), seq=3)
    client.send(*scans[1], seq=4)
    assert wait_until(lambda: client.seqs() == [4], TIMEOUT)
    assert wait_until(lambda: svc.counters.get("scans") == 1, TIMEOUT)  # counted just after the put (a race)
    c = svc.counters.snapshot()
    assert c["rejected.points"] == 3 and c["over_limit.points"] == 3 and c["scans"] == 1
    assert c.get("detect_errors", 0) == 0


def test_a_scan_over_max_scan_bytes_is_refused_unread(zenoh_port: int, client_session: zenoh.Session,
                                                     detector: Detector, scans) -> None:
    """Every other hot reader refuses a payload over its bound before reading it; the detector's ``points`` too
    (a 61 MiB scan was decoded and run, 1 GB of memory, with up to ten such held for stacked sweeps)."""
    detector.gate.set()
    svc = DetectorService(loopback_options(NS, zenoh_port, listen_self=True), detector, max_scan_bytes=1 << 20)
    try:
        client = Client(client_session)
        assert wait_until(lambda: client.pub.matching_status.matching, TIMEOUT)
        big = np.tile(scans[0][0], (3, 1))  # about 1.3 MB of points
        assert len(big) * 5 * 4 > 1 << 20
        client.send(big, scans[0][1], seq=1)
        client.send(*scans[1], seq=2)
        assert wait_until(lambda: client.seqs() == [2], TIMEOUT)
        assert wait_until(lambda: svc.counters.get("scans") == 1, TIMEOUT)  # counted just after the put
        c = svc.counters.snapshot()
        assert c["rejected.points"] == 1 and c["over_limit.points"] == 1 and c["scans"] == 1
    finally:
        svc.close()


def test_detections_the_trackers_reader_would_refuse_are_dropped_not_published() -> None:
    """One detection beyond the wire's limits would make the tracker refuse the whole frame: it is dropped."""
    from jitterguard.schemas import read_detected_objects
    from jitterguard.services.detector.adapter import detections_payload, detections_within_limits
    from jitterguard.schemas.wire import Limits
    from jitterguard.services.detector.config import Detections3D

    boxes = np.zeros((4, 9), np.float32)
    boxes[:, 3:6] = (4.0, 1.8, 1.5)
    boxes[1, 0] = 2e7  # beyond max_abs_coordinate_m
    boxes[2, 7] = 5e3  # beyond max_abs_speed_mps
    log_var = np.zeros((4, 5), np.float32)
    log_var[3, 0] = 20.0  # a variance of e^20 > max_variance
    det = Detections3D(boxes=boxes, scores=np.full(4, 0.9, np.float32), labels=np.zeros(4, np.int64),
                       log_variances=log_var)
    kept, dropped = detections_within_limits(det)
    assert dropped == 3 and len(kept) == 1
    header = Header(stamp=STAMP0, frame_id="lidar", seq=0)
    with pytest.raises(DecodeError):  # what the tracker did with the frame before
        read_detected_objects(detections_payload(det, header, Pose()))
    assert len(read_detected_objects(detections_payload(kept, header, Pose())).objects) == 1
    # judged by the readers' own rule, whatever the limits: each row alone is refused by a reader iff it is dropped
    tight = Limits(max_abs_coordinate_m=100.0, max_abs_speed_mps=10.0, max_variance=2.0)
    boxes[1, 0], boxes[2, 7], log_var[3, 0] = 150.0, 12.0, 1.0  # each beyond tight only
    det = Detections3D(boxes=boxes, scores=np.full(4, 0.9, np.float32), labels=np.zeros(4, np.int64),
                       log_variances=log_var)
    assert detections_within_limits(det)[1] == 0
    for row in range(4):
        one = det.subset(np.arange(4) == row)
        dropped_alone = detections_within_limits(one, tight)[1] == 1
        try:
            read_detected_objects(detections_payload(one, header, Pose()), tight)
            refused = False
        except DecodeError:
            refused = True
        assert dropped_alone == refused == (row > 0), row  # e^1 > max_variance 2 in row 3


def test_a_scan_without_finite_points_still_closes_its_frame(harness) -> None:
    svc, client = harness
    pts = np.full((5, 5), np.nan, np.float32)
    client.send(pts, Pose(), seq=1)
    assert wait_until(lambda: client.seqs() == [1], TIMEOUT)
    assert client.got[0].objects == []
    c = svc.counters.snapshot()
    assert c["empty_scans"] == 1 and c["nonfinite_points"] == 5


class RecordingGatedDetector(GatedDetector):
    """The gated detector that also keeps what the worker handed the network."""

    inputs: list[np.ndarray]

    def detect(self, points: np.ndarray):  # type: ignore[override]
        self.inputs.append(points.copy())
        return super().detect(points)


def test_a_sweep_model_gets_every_arrived_scan_stacked_even_those_the_worker_skipped(
        zenoh_port: int, client_session: zenoh.Session) -> None:
    """A model trained on stacked sweeps (five point fields): the service holds every scan that arrives and stacks
    the one the worker takes with the earlier ones — the scans it skipped while the network was busy included —
    exactly as the offline evaluator's stacker does with the same scans. (Two frames 0.1 s apart sent 50 ms apart:
    the ego at 23 m/s, where the module's frames 0.5 s apart would be a pose jumping at 114 m/s, which clears the
    held sweeps.)"""
    scans = _cast((0, 1))
    from jitterguard.services.detector.adapter import scan_pose
    from jitterguard.services.detector.config import PRESETS
    from jitterguard.services.detector.inference import crop_box
    from jitterguard.services.detector.network import CenterPointNet
    from jitterguard.services.detector.sweeps import SweepStacker

    torch.manual_seed(0)
    net = CenterPointNet(PRESETS["lite"].model_copy(update={"num_point_features": 5}))
    det = RecordingGatedDetector(net, meta={"source": {"sweeps": 4}}, threads=1, score_threshold=0.05)
    det.gate, det.entered, det.inputs = threading.Event(), threading.Event(), []
    det.gate.clear()
    svc = DetectorService(loopback_options(NS, zenoh_port, listen_self=True), det)
    try:
        client = Client(client_session)
        assert wait_until(lambda: client.pub.matching_status.matching, TIMEOUT)
        sent = [client.send(*scans[0], seq=0)]
        assert det.entered.wait(TIMEOUT)  # the worker holds scan 0 inside the network
        sent += [client.send(*scans[seq % 2], seq=seq) for seq in range(1, 5)]
        assert wait_until(lambda: svc.counters.get("received") == 5, TIMEOUT)
        det.gate.set()
        assert wait_until(lambda: client.seqs() == [0, 4], TIMEOUT)
        assert wait_until(lambda: svc.counters.get("scans") == 2, TIMEOUT)
        c = svc.counters.snapshot()
        assert c["skipped_scans"] == 3 and c["stacked_sweeps_last"] == 4 and c["sweep_resets"] == 0
        # the ego pose jumps by 1 km: the held sweeps go, the heartbeat says so (they had been stacked a kilometre
        # off, out of range, and counted as four sweeps of the input)
        far = scans[1][1].model_copy(update={"position": Point(x=1000.0, y=0.0, z=1.84)})
        client.send(scans[1][0], far, seq=5)
        assert wait_until(lambda: svc.counters.get("scans") == 3, TIMEOUT)
        c = svc.counters.snapshot()
        assert c["stacked_sweeps_last"] == 1 and c["sweep_resets"] == 1
    finally:
        det.gate.set()
        svc.close()
    # offline: the same five scans through one stacker; the network saw scan 0 alone, then scan 4 with 3, 2, 1
    offline = SweepStacker(4)
    want = []
    for msg in sent:
        pts = np.frombuffer(msg.data, "<f4").reshape(msg.num_points, 5)[:, :4].copy()
        r, t = scan_pose(msg)
        offline.add(msg.header.stamp, r, t, crop_box(pts, det.self_crop))  # each sweep's body cropped in its frame
        want.append(offline.stack(msg.header.stamp, r, t, pts))
    assert len(det.inputs) == 3
    for got, exp in zip(det.inputs, (want[0], want[4])):
        np.testing.assert_array_equal(got, exp)
    lags = np.unique(det.inputs[1][:, 4])
    np.testing.assert_allclose(lags, [0.0, 0.05, 0.1, 0.15], atol=1e-6)


def client_cloud(pts: np.ndarray) -> PointCloud:
    return PointCloud(header=Header(stamp=STAMP0, frame_id="lidar", seq=0), fields=["x", "y", "z", "intensity", "ring"],
                      num_points=len(pts), data=pts.astype("<f4").tobytes())


# ------------------------------------------------------------------------------------------------ the CLI


def test_bench_detector_json_has_the_documented_shape() -> None:
    from typer.testing import CliRunner

    from jitterguard.cli import app

    res = CliRunner().invoke(app, ["bench", "detector", "--json", "--presets", "lite", "--scans", "2", "--warmup",
                                   "1", "--threads", "1", "--no-progress", "--backends", "torch"])
    assert res.exit_code == 0, res.output
    doc = json.loads(res.stdout.strip().splitlines()[-1])
    assert set(doc) == {"lite"}
    row = doc["lite"]
    assert row["points"] > 10_000  # a real HDL-32E scan, not a toy cloud
    assert 0 < row["p50_ms"] <= row["p99_ms"] and row["scans"] == 2 and row["threads"] == 1
    assert set(row["stages_ms"]) == {"voxelize", "network", "decode"}
    assert row["weights"] in ("shipped", "random-init") and row["device"] == "cpu" and row["sweeps"] == 1
    # stacks of three sweeps: about three scans' points through a widened (five-field) network
    res = CliRunner().invoke(app, ["bench", "detector", "--json", "--presets", "lite", "--scans", "2", "--warmup",
                                   "1", "--threads", "1", "--no-progress", "--backends", "torch", "--sweeps", "3"])
    assert res.exit_code == 0, res.output
    stacked = json.loads(res.stdout.strip().splitlines()[-1])["lite"]
    assert stacked["sweeps"] == 3 and stacked["weights"].endswith("(+ zero time-lag input)")
    assert stacked["points"] > 2 * row["points"]


@pytest.mark.parametrize(
    ("args", "needle"),
    [
        (["detector", "--preset", "huge"], "--preset"),
        (["detector", "--weights", "/nonexistent/lite.pt"], "not found"),
        (["detector", "--ns", "bad/ns"], "--ns"),
        (["detector", "--connect", "nonsense"], "endpoint"),
        (["detector", "--sensor-height", "tall"], "--sensor-height"),
        (["detector", "--sensor-height", "184"], "--sensor-height"),
        (["detector", "--sensor-height", "nan"], "--sensor-height"),
        (["detector", "--sensor-tilt", "pitched"], "--sensor-tilt: expected 'auto' or 'level'"),
        (["eval-detector", "--out", "/tmp/jg-never-written", "--sensor-tilt", "2"], "--sensor-tilt"),
        (["adapt", "--weights", "w.pt", "--out", "/tmp/jg-never-written", "--scans", "s", "--sensor-tilt", "x"],
         "--sensor-tilt"),
        (["bench", "detector", "--presets", "lite,huge"], "--presets"),
        (["bench", "detector", "--scenario", "moon"], "--scenario"),
        (["bench", "detector", "--weights", "lite"], "--weights"),
        (["bench", "detector", "--device", "gpu"], "--device"),
    ],
)
def test_bad_input_is_one_line_and_exit_2(args: list[str], needle: str) -> None:
    res = subprocess.run([sys.executable, "-m", "jitterguard.cli", *args], capture_output=True, text=True, timeout=60)
    assert res.returncode == 2, res.stderr
    lines = [ln for ln in res.stderr.strip().splitlines() if ln.strip()]
    assert len(lines) == 1 and needle in lines[0], res.stderr


@pytest.mark.parametrize("command", [["detector"], ["eval-detector", "--out", "{tmp}/ev"]])
def test_a_file_that_is_not_weights_is_refused_in_one_line(command: list[str], tmp_path: Path) -> None:
    """Said in jitterguard's words: torch's own message ran to six lines (eval-detector printed it whole) and
    advised loading the file with weights_only=False, which runs whatever code it holds."""
    bad = tmp_path / "lite.pt"
    bad.write_bytes(b"definitely not a torch file")
    args = [a.replace("{tmp}", str(tmp_path)) for a in command]
    res = subprocess.run([sys.executable, "-m", "jitterguard.cli", *args, "--weights", str(bad)],
                         capture_output=True, text=True, timeout=60)
    assert res.returncode == 2
    lines = [ln for ln in res.stderr.strip().splitlines() if ln.strip()]
    assert len(lines) == 1 and "--weights" in lines[0] and "lite.pt: not a jitterguard detector weights file" in lines[0]
    assert "weights_only" not in res.stderr, res.stderr


def test_a_preset_that_contradicts_the_weights_is_refused_in_one_line() -> None:
    """The weights file fixes the network: ``--preset paper`` beside lite weights had been ignored without a word
    (eval-detector and export-onnx refused it)."""
    from jitterguard.services.detector.inference import shipped_weights

    res = subprocess.run([sys.executable, "-m", "jitterguard.cli", "detector", "--weights", str(shipped_weights("lite")),
                          "--preset", "paper", "--connect", "tcp/127.0.0.1:9"], capture_output=True, text=True,
                         timeout=60)
    assert res.returncode == 2 and res.stderr.strip().startswith(
        "jitterguard: error: --preset: 'paper' contradicts --weights"), res.stderr


def test_detector_process_detects_and_stops_cleanly_on_sigterm(scans, client_session, zenoh_port) -> None:
    """``jitterguard detector`` as its own process: one scan in, one DetectedObjects out, SIGTERM exits 0."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "jitterguard.cli", "detector", "--ns", NS, "--listen", f"tcp/127.0.0.1:{zenoh_port}",
         "--threads", "1", "--score-threshold", "0.05"],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.extend(proc.stdout or []), daemon=True)
    reader.start()
    try:
        client = Client(client_session)
        assert wait_until(lambda: client.pub.matching_status.matching, TIMEOUT), "".join(lines)
        client.send(*scans[0], seq=11)
        assert wait_until(lambda: client.seqs() == [11], TIMEOUT), "".join(lines)
        assert len(client.got[0].objects) > 0
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=30)
        reader.join(timeout=5)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    out = "".join(lines)
    assert proc.returncode == 0, out
    assert "detector up" in out and "detector stopped" in out
