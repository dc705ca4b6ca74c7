"""What `jitterguard up` writes: arguments checked, paths absolute, and supervisord.conf read back by supervisord's
own parser exactly as meant (a newline cannot add a program, a '%' stays a '%')."""

from __future__ import annotations

import shlex
from pathlib import Path

import pytest
from supervisor.options import ServerOptions

from jitterguard.services.replay.options import ReplayOptions, absolute_source
from jitterguard.stack.supervisor import StackSpec, programs, render_config
from jitterguard.stack.validate import ArgumentError, check_name, check_run_dir, check_text


def parse(conf: Path) -> dict[str, list[str]]:
    """supervisord's own reading of the file: program name -> argv."""
    opts = ServerOptions()
    opts.realize(args=["-c", str(conf)])
    return {p.name: shlex.split(p.command) for g in opts.process_group_configs for p in g.process_configs}


def write(tmp_path: Path, spec: StackSpec) -> Path:
    rd = tmp_path / "run"
    (rd / "logs").mkdir(parents=True, exist_ok=True)
    conf = rd / "supervisord.conf"
    conf.write_text(render_config(spec, rd, programs(spec), nodaemon=True))
    return conf


def test_a_percent_and_spaces_in_source_and_options_reach_the_replay_as_given(tmp_path):
    src = "/data/50% run/%(ENV_HOME)s scans"
    spec = StackSpec(ns="x", name="x", router_port=1234, source=src, input="detections",
                     replay_args=("--topic", "/a%b", "--pose-topic", "/odom"), run_dir=str(tmp_path / "run"))
    argv = parse(write(tmp_path, spec))
    replay = argv["replay"]
    assert replay[3:5] == ["replay", src]
    assert replay[replay.index("--topic") + 1] == "/a%b" and "--pose-topic" in replay
    assert set(argv) == {"router", "classifier", "tracker", "sidecar", "replay", "monitor", "monitor-watch"}
    for name in ("monitor", "monitor-watch"):  # the watch's count lies beside the monitor's summary
        assert argv[name][argv[name].index("--run-dir") + 1] == str(tmp_path / "run")


@pytest.mark.parametrize("bad", ["a\nb", "x\r[program:evil]", "tab\tx", "nul\x00", "del\x7f"])
def test_control_characters_are_refused_before_rendering(tmp_path, bad):
    with pytest.raises(ArgumentError, match="control character"):
        check_text(bad, "SOURCE")
    spec = StackSpec(ns="x", source="/d/" + bad, input="detections", run_dir=str(tmp_path / "run"))
    with pytest.raises(ValueError, match="control character"):
        render_config(spec, tmp_path, programs(spec), nodaemon=True)


def test_a_newline_cannot_add_a_program(tmp_path):
    """What issue 18 found: SOURCE "x\\n[program:evil]\\ncommand=..." used to become a program run as root."""
    spec = StackSpec(ns="x", source="/d/x\n[program:evil]\ncommand=/bin/touch /tmp/pwned", input="detections")
    with pytest.raises(ValueError):
        render_config(spec, tmp_path, programs(spec), nodaemon=True)


def test_comment_starts_and_bad_names_are_refused():
    with pytest.raises(ArgumentError, match="comment"):
        check_text("/data/run ;x", "SOURCE")
    assert check_text("/data/run;x#y", "SOURCE") == "/data/run;x#y"  # without a space before, no comment
    for bad in ("", "-x", "a/b", "a b", "x" * 65):
        with pytest.raises(ArgumentError, match="--name"):
            check_name(bad)
    assert check_name("lidar-2.test_a") == "lidar-2.test_a"


def test_run_dir_is_absolute_and_refused_when_supervisord_could_not_use_it(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert check_run_dir(Path("rel/run")) == tmp_path / "rel" / "run"
    with pytest.raises(ArgumentError, match="'%'"):
        check_run_dir(Path("run%1"))
    with pytest.raises(ArgumentError, match="too long"):
        check_run_dir(tmp_path / ("x" * 120))


def test_relative_paths_become_absolute_against_the_current_folder(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert absolute_source("scans/../bag.mcap") == str(tmp_path / "bag.mcap")
    assert absolute_source("synthetic:mixed") == "synthetic:mixed"
    opts = ReplayOptions(poses="poses/00.txt", calib="/abs/calib.txt").absolute()
    assert opts.poses == str(tmp_path / "poses" / "00.txt") and opts.calib == "/abs/calib.txt"


def test_replay_options_give_only_the_flags_that_differ_and_the_replay_cli_takes_them():
    from jitterguard.cli import app
    from typer.testing import CliRunner

    opts = ReplayOptions(rate="2", topic="/t", sweeps=True, duration=60.0, limit=5)
    argv = opts.argv()
    assert argv == ["--rate", "2", "--limit", "5", "--duration", "60.0", "--sweeps", "--topic", "/t"]
    assert ReplayOptions().argv() == []
    # every flag the stack passes is one `jitterguard replay` declares (a renamed flag would fail here)
    res = CliRunner().invoke(app, ["replay", "--help"], terminal_width=200)
    for flag in [a for a in ReplayOptions(rate="2", start=1, limit=1, on_error="stop", level="detections", seed=1,
                                          duration=1.0, lidar="vlp16", hz=5.0, scene="s", nuscenes_version="v",
                                          sweeps=True, poses="p", calib="c", times="t", bin_fields="x,y,z",
                                          topic="/t", pose_topic="/p").argv() if a.startswith("--")]:
        assert flag in res.output, flag


def test_a_port_left_in_time_wait_by_a_stopped_stack_is_free_and_a_listener_is_not():
    """`up` right after a run: the router's old connections sit in TIME_WAIT on its port; binding there works
    for the next router (it sets SO_REUSEADDR), so the check must not refuse it. A live listener still counts."""
    import socket

    from jitterguard.stack.validate import port_in_use

    server = socket.socket()
    server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    server.bind(("127.0.0.1", 0))
    server.listen()
    port = server.getsockname()[1]
    assert port_in_use("127.0.0.1", port)
    client = socket.create_connection(("127.0.0.1", port))
    conn, _ = server.accept()
    conn.close()  # the server side closes first: its end (on `port`) goes to TIME_WAIT
    client.close()
    server.close()
    assert not port_in_use("127.0.0.1", port)


def test_each_services_param_file_reaches_that_service_alone(tmp_path):
    """``up --classifier-config/--tracker-config/--detector-config``: each file goes to its own program's
    ``--config``, with a space and a '%' in its path kept as given."""
    files = {s: str(tmp_path / f"my 50% {s}.param.yaml") for s in ("classifier", "tracker", "detector")}
    spec = StackSpec(ns="x", name="x", input="points", run_dir=str(tmp_path / "run"), service_configs=files)
    argv = parse(write(tmp_path, spec))
    for service, path in files.items():
        assert argv[service][argv[service].index("--config") + 1] == path
    assert all("--config" not in a for n, a in argv.items() if n not in files)
    plain = parse(write(tmp_path, StackSpec(ns="x", name="x", input="points", run_dir=str(tmp_path / "run"))))
    assert all("--config" not in a for a in plain.values())


@pytest.mark.parametrize(("flag", "text", "extra", "needle"), [
    ("--classifier-config", "window_size: 7\nwindw: 1\n", (), "--classifier-config: .*windw: Extra inputs"),
    ("--tracker-config", "confirm_hits: '3'\n", (), "--tracker-config: .*confirm_hits"),
    ("--detector-config", "weights: runs/w.pt\n", (), "--detector-config: weights: runs/w.pt is relative"),
    ("--classifier-config", "calibration: file\ncalibration_file: /nonexistent/c.yaml\n", (),
     "--classifier-config: calibration_file: "),
    ("--detector-config", "threads: 2\n", ("--input", "detections"), "--detector-config: this stack runs no detector"),
    # what the detector refuses at its own start had started the whole stack, then crashed the detector three times
    ("--detector-config", "preset: bogus\n", (), "--detector-config: .*p.yaml: preset: expected one of"),
    ("--detector-config", "weights: /nonexistent/w.pt\n", (), "--detector-config: .*p.yaml: weights: file not found"),
])
def test_a_bad_service_file_stops_up_before_anything_starts(tmp_path, flag, text, extra, needle):
    import os
    import re
    import subprocess
    import sys

    from jitterguard.runtime import free_tcp_port

    f = tmp_path / "p.yaml"
    f.write_text(text)
    res = subprocess.run([sys.executable, "-m", "jitterguard.cli", "up", "--run-dir", str(tmp_path / "run"),
                          "--router-port", str(free_tcp_port()), "--port", str(free_tcp_port()), *extra, flag, str(f)],
                         capture_output=True, text=True, timeout=120,
                         env={**os.environ, "XDG_RUNTIME_DIR": str(tmp_path / "xdg")})
    lines = res.stderr.strip().splitlines()
    assert res.returncode == 2 and len(lines) == 1 and re.search(needle, lines[0]), res.stderr
    assert not (tmp_path / "run" / "supervisord.conf").exists()  # nothing was written, nothing started


@pytest.mark.parametrize(("level", "consumer"), [("points", "detector"), ("detections", "tracker")])
def test_the_replay_waits_for_the_pipelines_first_stage_not_any_subscriber(tmp_path, level, consumer):
    """With --foxglove or --record-ros2 the bridge subscribed first and the replay started before the detector was
    up: its first scans never reached it, and the summary said none was dropped."""
    spec = StackSpec(ns="x", name="x", router_port=1234, input=level, foxglove=True, run_dir=str(tmp_path / "run"))
    replay = parse(write(tmp_path, spec))["replay"]
    assert replay[replay.index("--wait-for") + 1] == consumer
    assert float(replay[replay.index("--wait-subscriber") + 1]) >= 60
