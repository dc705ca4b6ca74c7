"""`jitterguard up` as an operator meets it, under a real supervisord with real processes (issue 19).

Two named stacks run side by side at detection level (no detector, so they start fast): one from a bag given by
a relative path with --topic/--pose-topic, one from a nuScenes-format dataroot whose annotated boxes go through
the noise model (--input detections), at a path holding a '%' and a space. Around them: sources
and arguments refused before anything starts, a third stack refused on a port in use, status/down/summary
in every state, a replay driven into BACKOFF, and a foreground stack stopped by a crash loop.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from jitterguard.runtime import free_tcp_port
from jitterguard.stack.control import Supervisor
from jitterguard.sim.export import export_scenario
from jitterguard.sim.world import make_scenario
from replay.bagfixture import DET_TOPIC, ODOM_TOPIC, write_bag

from helpers import wait_until

pytestmark = pytest.mark.integration


def jg(*args: str, cwd: Path | None = None, env: dict[str, str] | None = None,
       timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "jitterguard.cli", *args], capture_output=True, text=True,
                          timeout=timeout, cwd=cwd, env=env)


def one_line(res: subprocess.CompletedProcess) -> str:
    """The command said exactly one line (stdout and stderr together) and no traceback."""
    text = (res.stdout + res.stderr).strip()
    assert "Traceback" not in text and len(text.splitlines()) == 1, text
    return text


@pytest.fixture(scope="module")
def stacks(tmp_path_factory):
    """Stacks 'a' (relative bag path) and 'b' (a '%' in its path) under a private $XDG_RUNTIME_DIR."""
    home = tmp_path_factory.mktemp("up")
    env = {**os.environ, "XDG_RUNTIME_DIR": str(home / "xdg")}
    data = home / "data"
    data.mkdir()
    write_bag(data / "bag_a", n=20)
    weird = home / "50% data" / "nu scenes"
    weird.parent.mkdir()
    export_scenario(make_scenario("parking-street", 1, duration_s=3.0, rate_hz=2.0), str(weird), seed=1)
    ports = {s: free_tcp_port() for s in ("a", "b")}  # the routers' (no sidecar: `--port` is refused with it)
    info = {"home": home, "env": env, "ports": ports, "bag_a": data / "bag_a", "bag_b": weird,
            "run": {s: home / "xdg" / "jitterguard" / s for s in ("a", "b")}}
    started = []
    try:
        for name, src, cwd, extra in (("a", "bag_a", data, ("--topic", DET_TOPIC, "--pose-topic", ODOM_TOPIC)),
                                      ("b", str(weird), None, ("--input", "detections", "--seed", "2"))):
            res = jg("up", src, "-d", "--name", name, "--ns", f"up{name}{os.getpid()}", "--router-port",
                     str(ports[name]), "--no-sidecar", *extra, cwd=cwd, env=env)
            info[f"up_{name}"] = res
            assert res.returncode == 0, res.stdout + res.stderr
            started.append(name)
        yield info
    finally:
        for name in started:
            jg("down", "--name", name, env=env)


def _status(info, name: str, *extra: str) -> subprocess.CompletedProcess:
    return jg("status", "--name", name, "--json", *extra, env=info["env"])


def test_a_relative_source_with_replay_options_runs(stacks):
    # started means progress: classified objects came, not only every program RUNNING
    assert re.search(r"jitterguard: started .*; first classified objects after \d+\.\d s", stacks["up_a"].stdout), \
        stacks["up_a"].stdout
    rows: dict = {}

    def classified() -> bool:
        res = _status(stacks, "a")
        rows.update({r["name"]: r for r in json.loads(res.stdout)["services"]})
        return res.returncode == 0 and rows["classifier"]["counters"].get("frames_processed", 0) > 0

    assert wait_until(classified, timeout=60, period=1.0), rows
    assert set(rows) == {"router", "tracker", "classifier", "replay", "monitor", "monitor-watch"}  # no detector
    conf = (stacks["run"]["a"] / "supervisord.conf").read_text()
    assert str(stacks["bag_a"]) in conf and f"--topic {DET_TOPIC}" in conf  # made absolute, passed through


def test_nuscenes_boxes_run_live_from_a_path_with_a_percent_and_a_space(stacks):
    def frames() -> int:
        res = jg("summary", "--name", "b", "--json", env=stacks["env"])
        return (json.loads(res.stdout)["frames"]["classified"] or 0) if res.returncode == 0 else 0

    log = stacks["run"]["b"] / "logs" / "replay.log"
    assert wait_until(lambda: frames() > 5, timeout=60, period=1.0), log.read_text()
    assert "boxes through the detection-level noise model (seed 2)" in log.read_text()
    assert "--level detections" in (stacks["run"]["b"] / "supervisord.conf").read_text()


def test_a_second_stack_on_a_port_in_use_or_under_a_running_name_is_refused(stacks):
    res = jg("up", "-d", "--name", "c", "--ns", "upc", "--router-port", str(stacks["ports"]["b"]), "--no-sidecar",
             "--input", "detections", env=stacks["env"])
    assert res.returncode == 2 and "in use by the stack 'b'" in one_line(res)
    assert not (stacks["run"]["a"].parent / "c").exists()  # nothing written
    res = jg("up", "-d", "--name", "a", "--router-port", str(free_tcp_port()), "--no-sidecar", "--input",
             "detections", env=stacks["env"])
    assert res.returncode == 2 and "already running" in one_line(res)


def test_a_router_port_of_a_running_stack_is_refused_while_its_router_does_not_listen(stacks):
    """A stack's router port is its own while its router does not listen: just started (it binds seconds after
    supervisord starts it: 14 s on a loaded machine) or being restarted after a crash. A second `up` on that port
    in between had found it free and started a stack whose services ran through the other stack's router, while
    that stack's router (and later its own) waited for the port for ever."""
    sup = Supervisor(stacks["run"]["b"])
    sup.call("stopProcess", "router")  # as in a router's restart: its supervisord runs, nothing listens
    try:
        res = jg("up", "-d", "--name", "c2", "--ns", "upc2", "--router-port", str(stacks["ports"]["b"]),
                 "--no-sidecar", "--input", "detections", env=stacks["env"])
        if res.returncode == 0:
            jg("down", "--name", "c2", env=stacks["env"])
        assert res.returncode == 2 and "in use by the stack 'b'" in one_line(res), res.stdout + res.stderr
        assert not (stacks["run"]["a"].parent / "c2").exists()  # nothing written
    finally:
        sup.call("startProcess", "router")


def test_a_stale_run_dir_whose_pid_names_another_stacks_supervisord_is_stale_not_that_stack(stacks):
    """After a reboot or a container restart the pids come again in the same order: a run dir left by a killed
    stack (its socket file and pid file still there) names a pid that is now another stack's supervisord. It had
    been taken for this stack "starting or stopping": `up` refused to start over it, and `down` exited 1 telling
    the operator to `kill` the other stack's supervisord."""
    import socket as so

    from jitterguard.stack.control import read_pid

    rd = stacks["run"]["a"].parent / "killed"
    rd.mkdir(mode=0o700)
    (rd / "logs").mkdir(mode=0o700)
    shutil.copy(stacks["run"]["a"] / "supervisord.conf", rd / "supervisord.conf")  # as its own `up` wrote it
    with so.socket(so.AF_UNIX, so.SOCK_STREAM) as sock:  # a socket file nothing listens on, as a SIGKILL leaves it
        sock.bind(str(rd / "supervisor.sock"))
    other = read_pid(stacks["run"]["b"])
    (rd / "supervisord.pid").write_text(f"{other}\n")
    try:
        res = jg("status", "--name", "killed", "--json", env=stacks["env"])
        assert res.returncode == 3 and json.loads(res.stdout)["state"] == "stale", res.stdout
        res = jg("down", "--name", "killed", env=stacks["env"])
        assert res.returncode == 0 and "died without cleaning up" in one_line(res), res.stdout + res.stderr
        assert Supervisor(stacks["run"]["b"]).running() and read_pid(stacks["run"]["b"]) == other
    finally:
        shutil.rmtree(rd)


def test_summary_adds_up_the_run(stacks):
    assert wait_until(lambda: jg("summary", "--name", "a", "--json", env=stacks["env"]).returncode == 0, timeout=30)
    data = json.loads(jg("summary", "--name", "a", "--json", env=stacks["env"]).stdout)
    assert data["stack"] == "a" and data["frames"]["replayed"] > 0 and data["tracks"]["born"] > 0
    assert 0 < data["tracks"]["confirmed"] <= data["tracks"]["born"]  # the tentative births are told apart
    assert 0 <= data["tracks"]["confirmed_ended"] <= min(data["tracks"]["ended"], data["tracks"]["confirmed"])
    assert data["rejected_total"] == 0 and "ledger" not in data
    # the 2 s bag (20 frames) has looped: seq and stamps go on across passes, so every frame is taken downstream
    # with no restart anywhere (each pass had begun seq again as a restarted source)
    assert data["frames"]["replayed"] > 20
    assert data["restarts"]["source_restarts"] == 0 and data["restarts"]["tracker_resets"] == 0
    assert data["restarts"]["classifier_upstream_restarts"] == 0
    assert not {k for k in data["dropped"] if k.startswith("tracker.dropped")}, data["dropped"]  # none held or late
    # heartbeats come each second: the tracker's count may trail the replay's by that much (10 Hz), and no more
    assert data["frames"]["tracked"] >= data["frames"]["replayed"] - 15
    text = jg("summary", "--name", "a", env=stacks["env"]).stdout
    assert "run summary of stack 'a'" in text and "tracks    born" in text
    assert re.search(r"born [\d,]+ \([\d,]+ confirmed\), ended [\d,]+ \([\d,]+ confirmed\)", text), text


def test_a_replay_in_backoff_makes_status_exit_3(stacks):
    """The bag disappears and the replay is killed: its restarts fail (no such file), supervisord backs off."""
    sup = Supervisor(stacks["run"]["a"])
    pid = next(p.pid for p in sup.processes() if p.name == "replay")
    shutil.rmtree(stacks["bag_a"])
    os.kill(pid, signal.SIGKILL)
    assert wait_until(lambda: any(p.name == "replay" and p.state in ("BACKOFF", "FATAL") for p in sup.processes()),
                      timeout=60, period=0.3)
    res = jg("status", "--name", "a", env=stacks["env"])
    assert res.returncode == 3, res.stdout
    replay = next(line for line in res.stdout.splitlines() if line.startswith("replay"))
    assert any(s in replay for s in ("BACKOFF", "STARTING", "FATAL")), replay  # retrying, never RUNNING
    log = (stacks["run"]["a"] / "logs" / "replay.log").read_text()
    assert "no such file or folder" in log


def test_down_then_status_summary_and_down_again_say_one_line(stacks):
    """While `down` stops the stack, `status` (asked over and over) answers with a table or one line, never a
    traceback; afterwards every command says one line."""
    env = stacks["env"]
    proc = subprocess.Popen([sys.executable, "-m", "jitterguard.cli", "down", "--name", "b"], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    seen = []
    while proc.poll() is None:
        st = jg("status", "--name", "b", "--listen-s", "0.2", env=env)
        assert "Traceback" not in st.stdout + st.stderr and st.returncode in (0, 3), st.stdout + st.stderr
        seen.append(st.stdout.splitlines()[0] if st.stdout else "")
    out, err = proc.communicate()
    print(f"\nstatus while stopping: {seen}")
    assert proc.returncode == 0 and "stopped" in out and "run summary" in out, out + err
    st = jg("status", "--name", "b", env=env)
    assert st.returncode == 3 and "not running" in one_line(st)
    again = jg("down", "--name", "b", env=env)
    assert again.returncode == 0 and "not running" in one_line(again)
    assert "run summary" in jg("summary", "--name", "b", env=env).stdout  # the last run's, after down


def test_no_stack_at_all_is_one_line_everywhere(tmp_path):
    env = {**os.environ, "XDG_RUNTIME_DIR": str(tmp_path)}
    st = jg("status", "--name", "ghost", env=env)
    assert st.returncode == 3 and "no stack 'ghost'" in one_line(st)
    js = jg("status", "--name", "ghost", "--json", env=env)
    assert js.returncode == 3 and json.loads(js.stdout)["state"] == "absent"
    assert jg("down", "--name", "ghost", env=env).returncode == 0
    sm = jg("summary", "--name", "ghost", env=env)
    assert sm.returncode == 1 and "no summary" in one_line(sm)
    lg = jg("logs", "tracker", "--name", "ghost", env=env)
    assert lg.returncode == 2 and "no log" in one_line(lg)


def _refused(tmp_path: Path, *args: str) -> tuple[subprocess.CompletedProcess, float]:
    env = {**os.environ, "XDG_RUNTIME_DIR": str(tmp_path / "xdg")}
    t0 = time.monotonic()
    res = jg("up", *args, "--name", "bad", "--router-port", str(free_tcp_port()), "--no-sidecar", env=env,
             cwd=tmp_path, timeout=60)
    elapsed = time.monotonic() - t0
    assert res.returncode == 2, res.stdout + res.stderr
    assert not (tmp_path / "xdg").exists(), "up wrote a run directory for a refused source"
    return res, elapsed


def test_sources_that_cannot_be_replayed_are_refused_before_anything_starts(tmp_path):
    """Each answer is the reader's own line, in seconds (the old `up /nope/bag.mcap` waited 60 s)."""
    (tmp_path / "garbage.mcap").write_bytes(b"\x00 not an mcap file" * 10)
    write_bag(tmp_path / "bag", n=3)
    (tmp_path / "scans").mkdir()
    (tmp_path / "scans" / "000000.bin").write_bytes(b"\x00" * 10)  # not whole float32 points
    cases = [
        (("/nope/bag.mcap",), "no such file or folder"),
        (("garbage.mcap",), "garbage.mcap"),
        (("bag", "--topic", "/nope"), "no topic '/nope'"),
        (("scans",), "not a whole number"),
        (("scans", "--poses", "missing.txt"), "--poses: file not found"),
        (("scans", "--topic", "/x"), "--topic does not apply"),
        (("bag", "--scenario-duration", "30"), "--scenario-duration does not apply to a bag source"),
        (("synthetic:nope",), "unknown scenario"),
        (("bag", "--input", "points", "--topic", DET_TOPIC), "--input points needs scans"),
        # --start past the end: the replay would refuse it three times and the stack would be stopped
        (("bag", "--start", "3"), "--start 3 is past the end of"),
        (("synthetic:mixed", "--scenario-duration", "1", "--start", "10"), "--start 10 is past the end of synthetic:mixed"),
        (("--scenario-duration", "-5"), "--scenario-duration must be in (0, 600]"),  # not up's own --duration
    ]
    times = {}
    for args, reason in cases:
        res, elapsed = _refused(tmp_path, *args)
        assert reason in one_line(res), (args, res.stderr)
        times[" ".join(args)] = round(elapsed, 2)
    print(f"\nrefusal times (s): {json.dumps(times)}")


def _pcd_scans(folder: Path, viewpoints: list[str]) -> Path:
    """A folder of small ASCII PCD scans, one per VIEWPOINT (tx ty tz qw qx qy qz) given."""
    folder.mkdir()
    rows = "".join(f"{x:.2f} {y:.2f} 0.5\n" for x, y in np.random.default_rng(0).uniform(-20, 20, (64, 2)))
    for i, vp in enumerate(viewpoints):
        (folder / f"{i:04d}.pcd").write_text(f"VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\n"
                                             f"WIDTH 64\nHEIGHT 1\nVIEWPOINT {vp}\nPOINTS 64\nDATA ascii\n{rows}")
    return folder


def test_a_recording_whose_every_ego_pose_the_replay_refuses_is_refused_before_anything_starts(tmp_path):
    """The probe took the first frame that read, though the replay then refuses its ego pose (not finite, beyond
    max_abs_coordinate_m): `up` wrote the run directory, started the whole stack, and stopped it 20 s later on the
    replay's crash loop ("no frame could be read"), exit 1. The replay's own pose rule now goes into the probe."""
    _pcd_scans(tmp_path / "nan_poses", ["nan 0 0 1 0 0 0"] * 3)
    _pcd_scans(tmp_path / "far_poses", ["1e9 0 0 1 0 0 0"] * 3)
    for src, reason in (("nan_poses", "0000.pcd: ego pose is not finite"),
                        ("far_poses", "0000.pcd: ego_pose.position: beyond max_abs_coordinate_m")):
        res, _ = _refused(tmp_path, src)
        assert reason in one_line(res), res.stderr


def test_the_probe_skips_frames_with_refused_poses_as_the_replay_does(tmp_path):
    """One bad pose among good ones is a skipped frame in the replay, so the probe takes the recording."""
    from jitterguard.services.replay.sources import probe_source

    folder = _pcd_scans(tmp_path / "mixed", ["nan 0 0 1 0 0 0", "0 0 0 1 0 0 0", "0 0 0 1 0 0 0"])
    assert probe_source(str(folder)).num_frames == 3


@pytest.mark.parametrize("bad", ["synthetic:mixed\n[program:evil]\ncommand=/bin/touch {flag}", "x\x1b[31m"])
def test_a_source_with_control_characters_starts_nothing(tmp_path, bad):
    flag = tmp_path / "pwned"
    res, _ = _refused(tmp_path, bad.format(flag=flag))
    assert "SOURCE: control character" in one_line(res)
    assert not flag.exists()  # nothing was started that could have run it (no run directory: _refused)


@pytest.mark.parametrize("flag", ["--topic", "--scene", "--lidar", "--poses"])
def test_a_replay_option_with_a_control_character_is_refused_naming_its_flag(tmp_path, flag):
    res, _ = _refused(tmp_path, flag, "x\n[program:evil]")
    assert f"{flag}: control character" in one_line(res)


def test_a_run_dir_is_made_for_its_user_alone(stacks):
    """Mode 0700, the run directory and its logs: it had been made with the umask's 0755."""
    for name in ("a", "b"):
        for d in (stacks["run"][name], stacks["run"][name] / "logs"):
            assert d.stat().st_mode & 0o777 == 0o700, (d, oct(d.stat().st_mode))


def test_a_run_dir_another_user_may_write_in_is_refused_before_anything_is_written(tmp_path):
    """`up --run-dir /tmp/shared` into a folder other users may write in (or own) had written supervisord.conf
    there and started supervisord on it: another user could replace the file before supervisord read it, or link
    a log file to any file for supervisord (root, if `up` is) to append to."""
    env = {**os.environ, "XDG_RUNTIME_DIR": str(tmp_path / "xdg")}
    shared = tmp_path / "shared"
    shared.mkdir()
    shared.chmod(0o777)
    cases = [(shared, "is writable by other users (mode 0777)"), (shared / "logs", "is writable by other users")]
    if os.geteuid() == 0:
        theirs = tmp_path / "theirs"
        theirs.mkdir(mode=0o755)
        os.chown(theirs, 65534, 65534)
        cases.append((theirs, "belongs to uid 65534, not to you"))
    for rd, reason in cases:
        if rd.name == "logs":  # a run dir of one's own whose logs folder others may write in
            rd.parent.chmod(0o755)
            rd.mkdir(mode=0o777)
            rd.chmod(0o777)
        target = rd.parent if rd.name == "logs" else rd
        res = jg("up", "--run-dir", str(target), "--router-port", str(free_tcp_port()), "--no-sidecar", "-d",
                 env=env, timeout=60)
        if res.returncode == 0:  # it started one: stop it before failing
            jg("down", "--run-dir", str(target), env=env)
        assert res.returncode == 2 and reason in one_line(res), res.stdout + res.stderr
        assert not (target / "supervisord.conf").exists()


def test_a_sidecar_off_loopback_without_a_token_is_refused_before_anything_starts(tmp_path):
    """The sidecar would refuse to bind and crash-loop; `up` says why first, with the sidecar's own reason."""
    env = {k: v for k, v in os.environ.items() if k != "JG_API_TOKEN"}
    env["XDG_RUNTIME_DIR"] = str(tmp_path / "xdg")
    res = jg("up", "--name", "open", "--host", "0.0.0.0", "--router-port", str(free_tcp_port()), "--port",
             str(free_tcp_port()), env=env, cwd=tmp_path, timeout=60)
    assert res.returncode == 2 and "--host: refusing to bind 0.0.0.0 without JG_API_TOKEN" in one_line(res)
    assert not (tmp_path / "xdg").exists()


@pytest.mark.parametrize("var, value, reason", [
    ("JG_CRASH_LOOP_EXITS", "abc", "JG_CRASH_LOOP_EXITS='abc' is not a number"),
    ("JG_CRASH_LOOP_BACKOFF_S", "-1", "JG_CRASH_LOOP_BACKOFF_S='-1': expected a number from 0.1"),
    ("JG_WATCHDOG_S", "inf", "JG_WATCHDOG_S='inf': expected at most"),
    ("JG_ZENOH_CONFIG", "/nope/zenoh.json5", "JG_ZENOH_CONFIG: zenoh config file not found: /nope/zenoh.json5")])
def test_a_malformed_variable_the_programs_read_is_refused_before_anything_starts(tmp_path, var, value, reason):
    """Each program refuses it at its start, after its imports: the monitor's had let `up -d` say "started" (it
    failed seconds after supervisord called it RUNNING) and then crash-looped beside the stack."""
    env = {**os.environ, var: value, "XDG_RUNTIME_DIR": str(tmp_path / "xdg")}
    res = jg("up", "--name", "env", "--input", "detections", "--no-sidecar", "--router-port", str(free_tcp_port()),
             "-d", env=env, cwd=tmp_path, timeout=120)
    if res.returncode == 0:
        jg("down", "--name", "env", env=env)
    assert res.returncode == 2 and reason in one_line(res), res.stdout + res.stderr
    assert not (tmp_path / "xdg").exists()


@pytest.mark.parametrize("host, reason", [("192.0.2.1", "Cannot assign requested address (not an address of this host)"),
                                          ("nonexistent.invalid", "cannot bind nonexistent.invalid")])
def test_a_sidecar_host_that_cannot_be_bound_is_refused_before_anything_starts(tmp_path, host, reason):
    """An address that is not this host's (a typo, an interface not up) or a name that does not resolve: `up` had
    started the whole stack, the sidecar crash-looped on "cannot bind", and the stack was stopped, exit 1."""
    env = {**os.environ, "JG_API_TOKEN": "t" * 32, "XDG_RUNTIME_DIR": str(tmp_path / "xdg")}
    res = jg("up", "--name", "nohost", "--input", "detections", "--host", host, "--router-port",
             str(free_tcp_port()), "--port", str(free_tcp_port()), "-d", env=env, cwd=tmp_path, timeout=120)
    if res.returncode == 0:
        jg("down", "--name", "nohost", env=env)
    assert res.returncode == 2 and "--host: cannot bind" in one_line(res) and reason in res.stderr, res.stderr
    assert not (tmp_path / "xdg").exists()


@pytest.mark.parametrize("port", ["8000", "0", "9123"])  # the default and "a free one" given too: any --port
def test_a_sidecar_port_without_a_sidecar_is_refused_before_anything_starts(tmp_path, port):
    """`--no-sidecar --port N` had started the stack and ignored N without a word."""
    res, _ = _refused(tmp_path, "--input", "detections", "--port", port)
    assert "--port is the sidecar's port; give it or --no-sidecar, not both" in one_line(res)
    assert [p.name for p in tmp_path.iterdir()] == []  # no run directory, no supervisord.conf anywhere here


def test_a_moving_sensor_without_poses_is_warned_about(tmp_path):
    from replay.helpers import write_bin

    import numpy as np

    (tmp_path / "scans").mkdir()
    for i in range(3):
        write_bin(tmp_path / "scans" / f"{i:06d}.bin", np.ones((10, 4), np.float32))
    env = {**os.environ, "XDG_RUNTIME_DIR": str(tmp_path / "xdg")}
    # a refused --port makes `up` stop right after the source check, so the warning is all that happens
    busy = free_tcp_port()
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", busy))
        s.listen()
        res = jg("up", "scans", "--name", "w", "--router-port", str(busy), env=env, cwd=tmp_path)
    assert res.returncode == 2 and "in use" in res.stderr
    assert "warning" in res.stderr and "no --poses" in res.stderr


def test_a_foreground_stack_whose_replay_crash_loops_stops_with_its_last_log_lines(tmp_path):
    write_bag(tmp_path / "bag", n=20)
    env = {**os.environ, "XDG_RUNTIME_DIR": str(tmp_path / "xdg")}
    proc = subprocess.Popen([sys.executable, "-m", "jitterguard.cli", "up", "bag", "--name", "fg", "--ns",
                             f"fg{os.getpid()}", "--router-port", str(free_tcp_port()), "--no-sidecar",
                             "--topic", DET_TOPIC, "--duration", "240"],
                            cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        first = proc.stdout.readline()
        assert "starting" in first, first + proc.stderr.read()
        line = proc.stdout.readline()
        assert "first classified objects" in line, line
        sup = Supervisor(tmp_path / "xdg" / "jitterguard" / "fg")
        pid = next(p.pid for p in sup.processes() if p.name == "replay")
        shutil.rmtree(tmp_path / "bag")
        os.kill(pid, signal.SIGKILL)
        out, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
            proc.wait(timeout=60)
    assert proc.returncode == 1, out + err
    assert "replay keeps failing" in err and "last lines of" in err and "no such file or folder" in err
    assert "run summary of stack 'fg'" in out and "unexpected exits: replay" in out
    assert not Supervisor(tmp_path / "xdg" / "jitterguard" / "fg").running()


def _foreground_up(tmp_path: Path, name: str, **popen: Any) -> tuple[subprocess.Popen, Path, dict[str, str]]:
    """A foreground ``up`` of a 20-frame bag (no sidecar, 240 s), once it has printed the first classified objects;
    (its process, run dir, environment)."""
    write_bag(tmp_path / "bag", n=20)
    env = {**os.environ, "XDG_RUNTIME_DIR": str(tmp_path / "xdg")}
    proc = subprocess.Popen([sys.executable, "-m", "jitterguard.cli", "up", "bag", "--name", name, "--ns",
                             f"{name}{os.getpid()}", "--router-port", str(free_tcp_port()), "--no-sidecar",
                             "--topic", DET_TOPIC, "--duration", "240"], cwd=tmp_path, env=env,
                            stdout=subprocess.PIPE, text=True, **popen)
    assert "starting" in proc.stdout.readline()
    assert "first classified objects" in proc.stdout.readline()
    return proc, tmp_path / "xdg" / "jitterguard" / name, env


@pytest.mark.parametrize("how", ["hangup", "sigkill"])
def test_a_foreground_stack_ends_with_its_up_when_the_terminal_hangs_up_or_up_is_killed(tmp_path, how):
    """An SSH session that drops sends SIGHUP to the terminal's process group: it had ended `up` at once and
    reached its supervisord as a "reload" — every program restarted, and the stack ran on unwatched past
    --duration. A `kill -9` of `up` had left the stack running for good. Now `up` stops the stack on a hangup as
    on Ctrl-C, and supervisord, in a session of its own, is sent SIGTERM by the kernel when `up` dies."""
    from jitterguard.stack.control import pid_alive, read_pid

    # a terminal's job: its own process group
    proc, rd, env = _foreground_up(tmp_path, "hup", stderr=subprocess.DEVNULL, start_new_session=True)
    try:
        sup_pid = read_pid(rd)
        programs = [p.pid for p in Supervisor(rd).processes() if p.pid]
        assert sup_pid and programs
        if how == "hangup":
            os.killpg(proc.pid, signal.SIGHUP)  # what the terminal's hangup sends its foreground job
        else:
            proc.kill()
        proc.wait(timeout=120)
        assert wait_until(lambda: not pid_alive(sup_pid) and not any(pid_alive(p) for p in programs),
                          timeout=120, period=0.5), "the stack ran on after its `up` was gone"
    finally:
        if proc.poll() is None:
            proc.kill()
        if Supervisor(rd).running():
            jg("down", "--name", "hup", env=env)
    assert not Supervisor(rd).running()


def test_a_foreground_up_whose_supervisord_dies_stops_what_it_left_and_says_so(tmp_path):
    """supervisord SIGKILLed under a foreground `up`: `up` had printed a run summary and exited 0 as if the run had
    finished, its programs running on unsupervised. It now stops them, says supervisord ended, and exits 1."""
    from jitterguard.stack.control import pid_alive, read_pid

    proc, rd, env = _foreground_up(tmp_path, "sdied", stderr=subprocess.PIPE)
    try:
        sup_pid = read_pid(rd)
        programs = [p.pid for p in Supervisor(rd).processes() if p.pid]
        assert sup_pid and programs
        os.kill(sup_pid, signal.SIGKILL)
        _out, err = proc.communicate(timeout=120)
        assert proc.returncode == 1, err
        assert "supervisord ended with status -9" in err and "stopped the programs it left running" in err, err
        assert wait_until(lambda: not any(pid_alive(p) for p in programs), timeout=60, period=0.5), \
            "programs ran on after their supervisord died"
    finally:
        if proc.poll() is None:
            proc.kill()
        if Supervisor(rd).running():
            jg("down", "--name", "sdied", env=env)


@pytest.mark.parametrize("how", ["interrupt", "down"])
def test_an_up_d_interrupted_or_stopped_while_it_starts_leaves_no_half_started_stack(tmp_path, how):
    """Ctrl-C to `up -d` while it waited had left the pipeline running without its monitor and sidecar (started
    only once the rest runs): no summary, no freeze watch, exit 130 in silence. It now stops what it started and
    says so. A `down` from another shell meanwhile had been waited out for 60 s, then called "left running"."""
    from jitterguard.stack.control import orphans

    write_bag(tmp_path / "bag", n=20)
    env = {**os.environ, "XDG_RUNTIME_DIR": str(tmp_path / "xdg")}
    rd = tmp_path / "xdg" / "jitterguard" / "half"
    proc = subprocess.Popen([sys.executable, "-m", "jitterguard.cli", "up", "bag", "-d", "--name", "half", "--ns",
                             f"half{os.getpid()}", "--router-port", str(free_tcp_port()), "--no-sidecar",
                             "--topic", DET_TOPIC], cwd=tmp_path, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        assert wait_until(lambda: Supervisor(rd).running(), timeout=60, period=0.2)
        if how == "interrupt":
            proc.send_signal(signal.SIGINT)
        else:
            assert jg("down", "--name", "half", env=env).returncode == 0
        _out, err = proc.communicate(timeout=60)  # at once, not after the 60 s wait for a start
        if how == "interrupt":
            assert proc.returncode == 130 and "interrupted (SIGINT) while the stack" in err, err
        else:
            assert proc.returncode == 1 and "the stack was stopped while it started" in err, err
        assert wait_until(lambda: not Supervisor(rd).running() and not orphans(rd), timeout=60, period=0.5)
    finally:
        if proc.poll() is None:
            proc.kill()
        if Supervisor(rd).running():
            jg("down", "--name", "half", env=env)


def _up_detached_killing_the_tracker(tmp_path: Path, name: str, *, after_s: float, kills: int, deadline_s: float,
                                     wait_s: float) -> tuple[int, str, str, Path]:
    """``up -d`` of a 20-frame bag whose tracker is SIGKILLed each time it has been RUNNING ``after_s`` (at most
    ``kills`` times, for at most ``deadline_s``); the stack is stopped after. Returns (exit status, stdout, stderr,
    run dir)."""
    write_bag(tmp_path / "bag", n=20)
    env = {**os.environ, "XDG_RUNTIME_DIR": str(tmp_path / "xdg")}
    rd = tmp_path / "xdg" / "jitterguard" / name
    proc = subprocess.Popen([sys.executable, "-m", "jitterguard.cli", "up", "bag", "-d", "--name", name, "--ns",
                             f"{name}{os.getpid()}", "--router-port", str(free_tcp_port()), "--no-sidecar",
                             "--topic", DET_TOPIC], cwd=tmp_path, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    running_since: dict[int, float] = {}
    killed: set[int] = set()
    try:
        deadline = time.monotonic() + deadline_s
        while proc.poll() is None and time.monotonic() < deadline and len(killed) < kills:
            try:
                tracker = next((p for p in Supervisor(rd).processes() if p.name == "tracker"), None)
            except Exception:  # supervisord not answering yet
                tracker = None
            if tracker is not None and tracker.state == "RUNNING" and tracker.pid not in killed:
                since = running_since.setdefault(tracker.pid, time.monotonic())
                if time.monotonic() - since >= after_s:
                    os.kill(tracker.pid, signal.SIGKILL)
                    killed.add(tracker.pid)
            time.sleep(0.05)
        out, err = proc.communicate(timeout=wait_s)
    finally:
        if proc.poll() is None:
            proc.kill()
        jg("down", "--name", name, env=env, cwd=tmp_path)
    return proc.returncode, out, err, rd


def test_a_detached_stack_whose_tracker_dies_after_starting_is_not_called_started(tmp_path):
    """A program that dies a second after supervisord calls it RUNNING, again and again: `up -d` had returned 0
    as soon as every program ran once; now it waits for every program to run crash-free for a while, sees the
    loop and stops the stack."""
    code, out, err, rd = _up_detached_killing_the_tracker(tmp_path, "slow", after_s=1.0, kills=4, deadline_s=60,
                                                          wait_s=60)
    assert code == 1, out + err
    assert "tracker keeps failing" in err and "unexpected exits" in err
    assert "started" not in out
    assert not Supervisor(rd).running()


def test_a_detached_stack_whose_tracker_dies_seconds_after_running_is_not_called_started(tmp_path):
    """A tracker that dies 4 s after supervisord calls it RUNNING, each time it is started: `up -d` had waited for
    3 s of every program RUNNING (supervisord's view, not the program's progress) and said "started" in between.
    Now a program that crashed while `up -d` waits must outlive its earlier life by the settle time, so the loop
    shows: the tracker is named, with the tail of its log, and the stack is stopped."""
    code, out, err, rd = _up_detached_killing_the_tracker(tmp_path, "late", after_s=4.0, kills=5, deadline_s=150,
                                                          wait_s=90)
    assert code == 1, out + err
    assert "jitterguard: started" not in out, out + err
    assert "tracker keeps failing" in err and f"last lines of {rd / 'logs' / 'tracker.log'}" in err, err
    assert not Supervisor(rd).running()


def _detached_bag_stack(tmp_path: Path, name: str, *, router_port: int | None = None,
                        run_dir: Path | None = None) -> tuple[dict[str, str], Path]:
    """``up -d`` of a 20-frame bag at detection level under a private $XDG_RUNTIME_DIR (or in ``run_dir``):
    (env, run dir)."""
    write_bag(tmp_path / "bag", n=20)
    env = {**os.environ, "XDG_RUNTIME_DIR": str(tmp_path / "xdg")}
    where = ["--run-dir", str(run_dir)] if run_dir else ["--name", name]
    res = jg("up", "bag", "-d", *where, "--ns", f"{name}{os.getpid()}", "--router-port",
             str(router_port or free_tcp_port()), "--no-sidecar", "--topic", DET_TOPIC, cwd=tmp_path, env=env)
    assert res.returncode == 0, res.stdout + res.stderr
    return env, run_dir or tmp_path / "xdg" / "jitterguard" / name


def test_a_port_held_by_a_stack_in_its_own_run_dir_names_that_stack(tmp_path):
    """A stack started with --run-dir is not under the stacks' folder: a clash with it had said 'another
    program'."""
    port = free_tcp_port()
    env, rd = _detached_bag_stack(tmp_path, "own", router_port=port, run_dir=tmp_path / "own-run")
    try:
        res = jg("up", "bag", "--run-dir", str(tmp_path / "other-run"), "--router-port", str(port), "--no-sidecar",
                 "--topic", DET_TOPIC, cwd=tmp_path, env=env)
        assert res.returncode == 2  # after the bag's warning about its poses, one line
        assert res.stderr.splitlines()[-1] == (f"jitterguard: error: port {port} on 127.0.0.1 is in use by the stack in {rd}; give"
                                 f" this stack another --router-port (or `jitterguard down --run-dir {rd}`)")
    finally:
        assert jg("down", "--run-dir", str(rd), cwd=tmp_path, env=env).returncode == 0


def test_a_stack_whose_run_dir_was_deleted_is_found_by_status_and_stopped_by_down(tmp_path):
    """$XDG_RUNTIME_DIR is removed at logout; the stack keeps running without its pid file and socket, and
    `status`/`down` had said there was no stack while its programs ran on."""
    env, rd = _detached_bag_stack(tmp_path, "gone")
    from jitterguard.stack.control import pid_alive, read_pid

    sup_pid = read_pid(rd)
    programs = [p.pid for p in Supervisor(rd).processes() if p.pid]
    shutil.rmtree(rd)
    try:
        res = jg("status", "--name", "gone", env=env, cwd=tmp_path)
        assert res.returncode == 3 and f"supervisord pid {sup_pid}" in one_line(res) and "was deleted" in res.stdout
        res = jg("down", "--name", "gone", env=env, cwd=tmp_path)
        assert res.returncode == 0 and "stopped" in one_line(res), res.stdout + res.stderr
        assert wait_until(lambda: not pid_alive(sup_pid) and not any(pid_alive(p) for p in programs), timeout=30)
        res = jg("status", "--name", "gone", env=env, cwd=tmp_path)
        assert res.returncode == 3 and "no stack" in one_line(res)
    finally:
        for pid in [sup_pid, *programs]:
            if pid_alive(pid):
                os.kill(pid, signal.SIGKILL)


def test_a_stack_whose_supervisord_died_is_reported_and_down_stops_what_it_left(tmp_path):
    env, rd = _detached_bag_stack(tmp_path, "orph")
    from jitterguard.stack.control import orphans, pid_alive, read_pid

    sup_pid = read_pid(rd)
    programs = {p.name: p.pid for p in Supervisor(rd).processes()}
    os.kill(sup_pid, signal.SIGKILL)
    try:
        assert wait_until(lambda: not Supervisor(rd).running() and not pid_alive(sup_pid), timeout=30)
        st = jg("status", "--name", "orph", env=env)
        assert st.returncode == 3 and "died without cleaning up" in one_line(st)
        # the programs run on unsupervised (one that writes to its log dies of the broken pipe; the router, which
        # logs nothing while it runs, certainly lives)
        left = orphans(rd)
        assert "router" in left and set(left) <= set(programs), (left, programs)
        again = jg("up", "bag", "-d", "--name", "orph", "--no-sidecar", "--topic", DET_TOPIC, "--pose-topic",
                   ODOM_TOPIC, cwd=tmp_path, env=env)
        assert again.returncode == 2 and "programs still run" in one_line(again)
        down = jg("down", "--name", "orph", env=env)
        assert down.returncode == 0 and "stopped its programs left running" in one_line(down)
        assert wait_until(lambda: not any(Path(f"/proc/{p}").exists() for p in programs.values()), timeout=30)
        assert "not running" in one_line(jg("status", "--name", "orph", env=env))
    finally:
        for pid in programs.values():
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass


def test_a_run_dir_writable_by_the_users_own_group_is_taken(tmp_path):
    """Under a umask of 002 (Ubuntu's user-private groups) every folder a user makes is 0775 in their own group: such
    a run dir is the user's alone and is taken; group-writable in another group, or world-writable, it is refused."""
    from jitterguard.stack.validate import ArgumentError, check_private_dir

    own = tmp_path / "own"
    own.mkdir()
    own.chmod(0o775)
    os.chown(own, -1, os.getegid())
    check_private_dir(own)  # no error
    if os.geteuid() == 0:
        other = tmp_path / "other"
        other.mkdir()
        other.chmod(0o775)
        os.chown(other, -1, 65534)
        with pytest.raises(ArgumentError, match="writable by other users"):
            check_private_dir(other)
    own.chmod(0o777)
    with pytest.raises(ArgumentError, match="writable by other users"):
        check_private_dir(own)
