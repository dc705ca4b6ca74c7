"""deploy/systemd/: every unit the target wants, started as systemd would start it from the shipped environment file,
makes a working pipeline — replay scans → detector → tracker → classifier → sidecar (real processes, real Zenoh on
loopback, real uvicorn; no systemd here, so no mocks of it either: what is emulated is only the variable expansion
of ``ExecStart=`` and ``EnvironmentFile=``).

What a test host cannot have is changed and nothing else: /var/lib/jitterguard becomes a temporary folder, the venv
path the one running this test, the ports free ones. Before, the units had no detector: a systemd install ran the
scenario's boxes, never a LiDAR scan, and a sensor host had no unit to run.
"""

from __future__ import annotations

import configparser
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest

from jitterguard.runtime import free_tcp_port

from helpers import wait_until

pytestmark = pytest.mark.integration

SYSTEMD = Path(__file__).resolve().parents[2] / "deploy" / "systemd"
TIMEOUT_S = 180.0


def environment_file(path: Path) -> dict[str, str]:
    """systemd's ``EnvironmentFile=`` for the lines this file uses: KEY=VALUE, comments and blank lines skipped."""
    env = {}
    for line in path.read_text().splitlines():
        line = line.strip()
        if line and not line.startswith("#"):
            key, _, value = line.partition("=")
            env[key.strip()] = value
    return env


def expand(command: str, env: dict[str, str]) -> list[str]:
    """``ExecStart=`` as systemd splits it: ``${VAR}`` one word, ``$VAR`` alone a word split at whitespace (none if
    empty)."""
    words: list[str] = []
    for word in command.split():
        bare = re.fullmatch(r"\$([A-Za-z_][A-Za-z0-9_]*)", word)
        if bare:
            words += env.get(bare.group(1), "").split()
        else:
            words.append(re.sub(r"\$\{([A-Za-z_][A-Za-z0-9_]*)\}", lambda m: env.get(m.group(1), ""), word))
    return words


def wanted_units() -> list[str]:
    target = configparser.ConfigParser(interpolation=None, strict=False)
    target.read(SYSTEMD / "jitterguard.target")
    return [u for u in target["Unit"]["Wants"].split() if u.startswith("jitterguard-")]


def _readyz(url: str) -> dict | None:
    try:
        return httpx.get(f"{url}/readyz", timeout=5.0).json()
    except (httpx.HTTPError, ValueError):
        return None


class Units:
    """The units started as systemd starts them from the shipped environment file, made local (module doc)."""

    def __init__(self, tmp_path: Path, units: list[str]) -> None:
        self.router, self.http = free_tcp_port(), free_tcp_port()
        shipped = environment_file(SYSTEMD / "jitterguard.env")
        self.env = {k: v.replace("tcp/127.0.0.1:7447", f"tcp/127.0.0.1:{self.router}")
                    .replace("/var/lib/jitterguard", str(tmp_path)).replace("--port 8000", f"--port {self.http}")
                    for k, v in shipped.items()}
        self.env["JG_NS"] = f"systemd{os.getpid()}"
        self.env["JG_REPLAY_ARGS"] += " --duration 30"  # the scenario ray-cast once, shorter than the default's 60 s
        self.url = f"http://127.0.0.1:{self.http}"
        venv_bin = str(Path(sys.executable).parent)
        base = {k: v for k, v in os.environ.items() if not k.startswith(("JG_", "SUPERVISOR_", "NOTIFY_SOCKET"))}
        self.procs: dict[str, subprocess.Popen] = {}
        self.logs: dict[str, Path] = {}
        # the router first (every unit is After= it), then the rest in the order given
        for unit in sorted(units, key=lambda u: u != "jitterguard-router.service"):
            cp = configparser.ConfigParser(interpolation=None, strict=False)
            cp.read(SYSTEMD / unit)
            svc = cp["Service"]
            assert svc["EnvironmentFile"] == "/etc/jitterguard/jitterguard.env"
            argv = expand(svc["ExecStart"], self.env)
            assert argv[0] == "/opt/jitterguard/venv/bin/jitterguard"
            argv[0] = f"{venv_bin}/jitterguard"
            name = unit.removeprefix("jitterguard-").removesuffix(".service")
            self.logs[name] = tmp_path / f"{name}.log"
            self.procs[name] = subprocess.Popen(argv, env={**base, **self.env}, cwd=tmp_path,
                                                stdout=self.logs[name].open("wb"), stderr=subprocess.STDOUT,
                                                start_new_session=True)

    def flowing(self, stages: tuple[str, ...] = ("detector", "tracker", "classifier")) -> bool:
        body = _readyz(self.url)
        if not body or not body.get("ready"):
            return False
        seen = body["services"]
        return all((seen.get(s, {}).get("last_seq") or 0) > 10 for s in stages)

    def tail(self) -> str:
        return "\n".join(f"--- {n} (rc {p.poll()})\n" + self.logs[n].read_text(errors="replace")[-1500:]
                         for n, p in self.procs.items())

    def stop(self) -> None:
        for p in self.procs.values():
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGTERM)
        for p in self.procs.values():
            try:
                p.wait(timeout=15)
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait(timeout=15)


def test_the_units_run_scans_through_the_detector_to_classified_objects(tmp_path):
    assert "jitterguard-detector.service" in wanted_units()
    units = Units(tmp_path, wanted_units())
    try:
        assert wait_until(units.flowing, timeout=TIMEOUT_S, period=1.0), units.tail()
        states: list[dict] = []

        def classified() -> bool:  # the looping replay starts the scene again: its first frames hold no tracks yet
            states.append(httpx.get(f"{units.url}/v1/state", timeout=5.0).json())
            return bool(states[-1]["tracks"]) and sum(states[-1]["counts"].values()) > 0
        assert wait_until(classified, timeout=30, period=0.5), states[-1]  # classified objects from detected scans
        assert all(p.poll() is None for p in units.procs.values()), units.tail()
    finally:
        units.stop()


def test_on_a_vehicle_the_ros2_units_take_the_replays_place(tmp_path):
    """``jitterguard-ros2-in`` and ``-ros2-out`` in place of the replay, as their units' header says: a ROS 2 side
    (played here by a Zenoh client putting CDR encoded by mcap-ros2-support, as zenoh-bridge-ros2dds would) sends a
    synthetic scenario's scans with /tf and /tf_static; Autoware's TrackedObjects come back on their topic's key,
    decoded by mcap-ros2-support, with the objects the classifier decided."""
    pytest.importorskip("mcap_ros2._dynamic")
    from jitterguard.eval.detector_input import synthetic_scans
    from jitterguard.runtime import ZenohOptions, build_config, open_session
    from jitterguard.sim.world import make_scenario
    from ros2_side import RosSide, codec

    env = environment_file(SYSTEMD / "jitterguard.env")
    points_topic = env["JG_ROS2_IN_ARGS"].split("--points-topic")[1].split()[0]
    out_topic = env["JG_ROS2_OUT_ARGS"].split("--topic")[1].split()[0]
    wanted = [u for u in wanted_units() if u != "jitterguard-replay.service"]
    units = Units(tmp_path, wanted + ["jitterguard-ros2-in.service", "jitterguard-ros2-out.service"])
    session = None
    try:
        session = open_session(build_config(ZenohOptions(ns=units.env["JG_NS"],
                                                         connect=(f"tcp/127.0.0.1:{units.router}",))))
        tracked = codec("autoware_perception_msgs/msg/TrackedObjects", encode=False)
        got: list = []
        session.declare_subscriber(out_topic.strip("/"), lambda s: got.append(tracked(s.payload.to_bytes())))
        ros = RosSide(session, points_topic)
        scans = list(synthetic_scans(make_scenario("parking-street", 0, 4.0, 10.0), 0))
        assert wait_until(lambda: (_readyz(units.url) or {}).get("ready", False), timeout=TIMEOUT_S, period=1.0), \
            units.tail()
        # /readyz is ready: every frame from now on must go through (a classifier still warming up had been called
        # ready while it dropped them). Two passes of the 4 s scenario, its stamps going on in time.
        for k in range(2):
            for ls in scans:
                ros.send(ls.scan, ls.scan.header.stamp + k * 5_000_000_000)
                time.sleep(0.1)
        assert wait_until(lambda: any(m.objects for m in got), timeout=60, period=0.5), units.tail()
        assert all(m.header.frame_id == "map" for m in got)
        assert units.flowing(("ros2-in", "detector", "tracker", "classifier")) or \
            wait_until(lambda: units.flowing(("ros2-in", "detector", "tracker", "classifier")), timeout=30), units.tail()
        assert all(p.poll() is None for p in units.procs.values()), units.tail()
    finally:
        if session is not None:
            session.close()
        units.stop()
