"""``jitterguard up --foxglove --record-mcap FILE --record-ros2 DIR`` under a real supervisord: the Foxglove server
answers on loopback, and ``down`` (SIGTERM) leaves a finished MCAP file and a complete ROS 2 bag."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest
import yaml
import zenoh

from jitterguard.runtime import ZenohOptions, build_config, free_tcp_port, open_session
from jitterguard.schemas import decode, keys
from jitterguard.schemas.models import Heartbeat
from jitterguard.stack.supervisor import StackSpec, programs

from helpers import wait_until

pytestmark = [pytest.mark.integration]


def jg(*args: str, timeout: float = 60) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "jitterguard.cli", *args], capture_output=True, text=True,
                          timeout=timeout)


def test_bridge_programs_join_the_stack_only_when_asked() -> None:
    base = {p.name for p in programs(StackSpec(input="detections"))}
    assert not base & {"foxglove", "record"}
    spec = StackSpec(input="detections", foxglove=True, foxglove_port=9999, record_mcap="/r/run.mcap",
                     record_ros2="/r/bag")
    progs = {p.name: p for p in programs(spec)}
    fox = " ".join(progs["foxglove"].args)
    assert "foxglove" in fox and "--port 9999" in fox and "--record /r/run.mcap --number-if-exists" in fox
    assert "--no-server" not in fox
    rec = " ".join(progs["record"].args)
    assert "record" in rec and "--ros2 /r/bag --number-if-exists" in rec
    assert progs["replay"].priority > progs["foxglove"].priority  # viewers up before the data starts
    only_mcap = {p.name: p for p in programs(StackSpec(input="detections", record_mcap="/r/x.mcap"))}
    assert "--no-server" in only_mcap["foxglove"].args


@pytest.mark.parametrize("args,needle", [
    (["foxglove", "--host", "0.0.0.0"], "--host"),
    (["foxglove", "--no-server"], "nothing to do"),
    (["foxglove", "--record", "/nonexistent-dir/run.mcap"], "--record"),
    (["record", "--ros2", "/nonexistent-dir/bag"], "--ros2"),
    (["record"], "--ros2"),
    (["up", "--record-ros2", "/nonexistent-dir/bag"], "--record-ros2"),
])
def test_bad_bridge_input_is_one_line_and_exit_2(args, needle) -> None:
    res = jg(*args)
    assert res.returncode == 2, res.stderr
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and needle in lines[0], res.stderr


def test_an_existing_recording_is_refused_not_overwritten(tmp_path) -> None:
    (tmp_path / "bag").mkdir()
    (tmp_path / "run.mcap").write_bytes(b"keep me")
    for args, flag in ((["record", "--ros2", str(tmp_path / "bag")], "--ros2"),
                       (["foxglove", "--record", str(tmp_path / "run.mcap")], "--record"),
                       (["up", "--record-mcap", str(tmp_path / "run.mcap")], "--record-mcap")):
        res = jg(*args)
        assert res.returncode == 2 and flag in res.stderr and "exists" in res.stderr
    assert (tmp_path / "run.mcap").read_bytes() == b"keep me"


@pytest.mark.slow
def test_up_with_foxglove_and_both_recordings_until_down(tmp_path) -> None:
    from websockets.sync.client import connect

    run_dir, bag, mcap_file = tmp_path / "run", tmp_path / "bag", tmp_path / "run.mcap"
    router, fox_port, ns = free_tcp_port(), free_tcp_port(), "stackfox"
    res = jg("up", "-d", "--ns", ns, "--input", "detections", "--router-port", str(router), "--no-sidecar",
             "--run-dir", str(run_dir), "--foxglove", "--foxglove-port", str(fox_port), "--record-mcap", str(mcap_file),
             "--record-ros2", str(bag))
    assert res.returncode == 0, res.stderr
    beats: dict[str, Heartbeat] = {}
    try:
        cfg = build_config(ZenohOptions(ns=ns, connect=(f"tcp/127.0.0.1:{router}",)))
        with open_session(cfg, timeout_s=60) as s:  # a client of the stack's router, which may be starting
            def on_beat(x: zenoh.Sample) -> None:
                hb = decode(Heartbeat, x.payload.to_bytes())
                beats[hb.service] = hb

            s.declare_subscriber(keys.heartbeat_all(ns), on_beat)
            ok = wait_until(lambda: all(beats.get(n) and beats[n].counters.get("frames", 0) >= 5
                                        for n in ("foxglove", "record")), timeout=90)
            assert ok, {n: (run_dir / "logs" / f"{n}.log").read_text()[-2000:] for n in ("foxglove", "record")}
        with connect(f"ws://127.0.0.1:{fox_port}", subprotocols=["foxglove.sdk.v1"], open_timeout=10) as ws:
            info = json.loads(ws.recv(timeout=5))
            assert info["op"] == "serverInfo" and info["name"] == "jitterguard"
    finally:
        down = jg("down", "--run-dir", str(run_dir))
    assert down.returncode == 0
    assert wait_until(lambda: not (run_dir / "supervisord.pid").exists(), timeout=30)
    meta = yaml.safe_load((bag / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    counts = {t["topic_metadata"]["name"]: t["message_count"] for t in meta["topics_with_message_count"]}
    assert counts["/perception/object_recognition/tracking/objects"] >= 5
    assert counts["/perception/object_recognition/detection/objects"] >= 5
    from mcap.reader import make_reader

    with open(mcap_file, "rb") as f:
        summary = make_reader(f).get_summary()  # only a finished file has a summary section
    assert summary is not None and summary.statistics.message_count > 0
    topics = {c.topic for c in summary.channels.values()}
    assert {"/jitterguard/tracks", "/jitterguard/motion", "/jitterguard/detections"} <= topics
