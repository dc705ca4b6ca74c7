"""Bad CLI input: one line on stderr and exit status 2, never a traceback."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

SHIPPED_WEIGHTS = Path(__file__).resolve().parents[2] / "jitterguard" / "services" / "detector" / "weights" / "lite.pt"

BLOCKED = f"{__file__}/sub"  # under a regular file: no folder can be made there
"""An ``--out`` that cannot be created must be refused before the work, not after it."""

CASES = [
    ["classifier", "--bogus"],
    ["classifier", "--log-level", "LOUD"],
    ["classifier", "--calibration", "off", "--calibration-file", "/nonexistent.yaml"],  # one would be ignored
    ["tracker", "--connect", "tcp/127.0.0.1:abc"],
    ["router", "--listen", "tcp/127.0.0.1:99999"],  # Zenoh would refuse it only on opening, retried for ever
    ["sim", "generate", "mixed", "--seed", "-1"],
    ["eval", "--out", BLOCKED, "--seed", "-1"],
    ["eval-study", "--out", BLOCKED, "--seeds", "1,-2"],
    ["eval", "--out", BLOCKED, "--duration", "2"],
    ["eval-study", "--out", BLOCKED],
    ["eval", "--out", "x", "--calibration", "online", "--calibration-file", "/nonexistent.yaml"],  # one ignored
    ["eval", "--out", "x", "--nuscenes", "/nonexistent", "--duration", "1"],  # a scene is scored whole
    ["train", "--out", BLOCKED],
    ["eval-detector", "--out", BLOCKED],
    ["export-onnx", "--out", BLOCKED],
    ["calibrate", "synthetic:mixed", "--duration", "5", "--out", f"{BLOCKED}/cal.yaml"],
    ["record", "--ros2", BLOCKED],
    ["render-mcap", __file__, "--out", "x.png"],  # not an MCAP file
    ["up", "--seed", "-1"],
    ["up", "-d", "--duration", "2"],  # a detached stack would ignore it
    ["up", "--router-port", "17448", "--port", "17448"],
    ["classifier", "--alpha", "-1"],
    ["classifier", "--mode", "zz"],
    ["classifier", "--ns", "a/b"],
    ["classifier", "--window-size", "3", "--min-window", "5"],
    ["classifier", "--config", "/nonexistent/x.yaml"],
    ["classifier", "--preset", "nope"],
    ["classifier", "--connect", "nonsense"],
    ["classifier", "--zenoh-config", "/nonexistent.json5"],
    ["bench", "classifier", "--tracks", "0"],
    ["feed-tracks", "--rate", "0"],
    ["up", "--input", "video"],
    ["logs", "classifier", "--run-dir", "/nonexistent-run-dir"],
    ["no-such-command"],
]


def run(args: list[str], cwd: Path | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "jitterguard.cli", *args], capture_output=True, text=True, timeout=60,
                          cwd=cwd)


@pytest.mark.parametrize("args", CASES, ids=[" ".join(c) for c in CASES])
def test_bad_input_is_one_line_and_exit_2(args):
    res = run(args)
    assert res.returncode == 2, res
    lines = [line for line in res.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, res.stderr
    assert "error" in lines[0] and "Traceback" not in res.stderr


def test_config_file_values_are_validated(tmp_path):
    cfg = tmp_path / "c.yaml"
    cfg.write_text("alpha_per_class: {spaceship: 2.0}\n")
    res = run(["classifier", "--config", str(cfg)])
    assert res.returncode == 2 and "alpha_per_class" in res.stderr


def test_help_lists_the_commands():
    res = run(["--help"])
    assert res.returncode == 0
    for cmd in ("classifier", "router", "up", "down", "status", "logs", "bench", "feed-tracks"):
        assert cmd in res.stdout


def test_an_unwritable_config_store_names_where_it_came_from(tmp_path):
    """``config_store`` is a field of the classifier's parameter file as well as a flag: a bad one is refused
    before anything starts, named as the user gave it."""
    bad = tmp_path / "no-such-dir" / "store.json"
    res = run(["classifier", "--config-store", str(bad)])
    assert res.returncode == 2 and res.stderr.count("\n") == 1 and "--config-store" in res.stderr
    cfg = tmp_path / "c.yaml"
    cfg.write_text(f"/**:\n  ros__parameters:\n    config_store: {bad}\n    open_config_writes: true\n")
    res = run(["classifier", "--config", str(cfg)])
    assert res.returncode == 2 and "config_store" in res.stderr and "--config-store" not in res.stderr


def test_an_unwritable_calibration_store_names_where_it_came_from(tmp_path):
    bad = tmp_path / "no-such-dir" / "cal.npz"
    res = run(["classifier", "--calibration-store", str(bad)])
    assert res.returncode == 2 and res.stderr.count("\n") == 1 and "--calibration-store" in res.stderr
    cfg = tmp_path / "c.yaml"
    cfg.write_text(f"calibration_store: {tmp_path}\n")  # a directory, not a file
    res = run(["classifier", "--config", str(cfg)])
    assert res.returncode == 2 and "calibration_store" in res.stderr and "--calibration-store" not in res.stderr


def test_help_shows_no_value_type_after_plain_flags():
    """`--detach` takes no value: the help must not print `<bool>` after it (nor after any other flag)."""
    for cmd in (["up", "--help"], ["replay", "--help"], ["status", "--help"]):
        res = subprocess.run([sys.executable, "-m", "jitterguard.cli", *cmd], capture_output=True, text=True,
                             timeout=60, env={**__import__("os").environ, "COLUMNS": "200"})
        assert res.returncode == 0 and "--" in res.stdout
        assert "<bool>" not in res.stdout, res.stdout


@pytest.mark.parametrize(("command", "text"), [
    ("bench track-survival", "Scenario length [s]"),  # Rich had taken "[s]" for markup and printed "length ."
    ("eval-study", "Scenario length [s]"),
    ("eval", "Synthetic scenario length [s]"),
    ("eval", "for every class [m/s] (default"),  # Rich had taken "[m/s]" for markup and dropped it
    ("eval-detector", "90 % intervals"),  # had printed "90 %%"
])
def test_help_shows_units_and_percent_signs_as_written(command, text):
    res = subprocess.run([sys.executable, "-m", "jitterguard.cli", *command.split(), "--help"], capture_output=True,
                         text=True, timeout=60, env={**__import__("os").environ, "COLUMNS": "250"})
    assert res.returncode == 0 and text in res.stdout, res.stdout


def test_each_service_command_is_registered_by_the_one_area_it_loads():
    """`jitterguard tracker` under supervisord imports only the tracker's area: the table must name the area
    that really registers the command, with the same options as in the full app."""
    import typer

    from jitterguard.cli import SERVICE_AREAS, app, build_app

    full = typer.main.get_command(app).commands
    for name, area in SERVICE_AREAS.items():
        alone = typer.main.get_command(build_app((area,))[0]).commands
        assert name in alone, (name, area)
        assert [p.name for p in alone[name].params] == [p.name for p in full[name].params]


@pytest.mark.parametrize(("args", "needle"), [
    (["render-mcap", __file__, "--out", "r.txt"], "--out must name a .png file"),  # had been a traceback
    (["render-mcap", __file__, "--out", "/proc/r.png"], "--out: cannot write /proc/r.png"),
    # /proc passes a folder test for root: calibrate had run the whole recording, then died writing
    (["calibrate", "synthetic:mixed", "--level", "detections", "--duration", "2", "--out", "/proc/x.yaml"],
     "--out: cannot write /proc/x.yaml"),
])
def test_an_output_that_cannot_be_written_is_refused_before_any_work(args, needle):
    res = run(args)
    reason = ": No such file or directory" if "cannot write" in needle else ""
    assert res.returncode == 2 and res.stderr.strip() == f"jitterguard: error: {needle}{reason}", res.stderr


@pytest.mark.parametrize(("args", "blocked"), [
    (["eval", "--scenario", "mixed", "--duration", "2", "--input", "gt-noise"], "report.md"),
    (["eval", "--scenario", "mixed", "--duration", "2", "--input", "gt-noise"], "metrics.json"),
    (["eval", "--scenario", "mixed", "--duration", "2", "--input", "gt-noise"], "speed_vs_z.png"),
    (["eval", "--scenario", "mixed", "--duration", "2", "--input", "gt-noise"], "run-0.mcap"),
    (["eval-study", "--seeds", "0", "--duration", "2"], "study.md"),
    (["eval-study", "--seeds", "0", "--duration", "2"], "diagonal-lot-clean/pr_curves.png"),
    # the detector's tools wrote their reports after the work too
    (["eval-detector", "--seeds", "1000"], "holdout_pr.png"),
    (["train", "--train-seeds", "0", "--val-seeds", "900", "--epochs", "1"], "history.json"),
    (["recalibrate-detector", "--weights", str(SHIPPED_WEIGHTS), "--seeds", "60"], "recalibration.json"),
])
def test_a_folder_where_an_output_file_goes_is_refused_before_any_work(args, blocked, tmp_path):
    """`eval --out X` with a folder X/report.md had run the whole evaluation, written metrics.json and the figures,
    then died on report.md with an IsADirectoryError traceback; a folder named like a stale run-*.mcap had died
    the same way at its unlink. Both are one line before the run now, and nothing is written."""
    out = tmp_path / "out"
    (out / blocked).mkdir(parents=True)
    (out / blocked / "keep.txt").write_text("mine\n")
    res = run([*args, "--out", str(out)])
    assert res.returncode == 2 and res.stderr.count("\n") == 1 and "Traceback" not in res.stderr, res.stderr
    assert f"--out: {out / blocked} is a folder" in res.stderr, res.stderr
    assert (out / blocked / "keep.txt").read_text() == "mine\n"
    assert not (out / "metrics.json").is_file() and not (out / "study.json").exists()


@pytest.mark.parametrize(("args", "needle"), [
    # negative seeds had been numpy tracebacks (SeedSequence), an empty list a ZeroDivisionError
    (["bench", "detector", "--seed", "-1"], "--seed: -1 is negative"),
    (["bench", "tracker", "--seed", "-1"], "--seed: -1 is negative"),
    (["bench", "pipeline", "--seed", "-1", "--duration", "1"], "--seed: -1 is negative"),
    (["bench", "track-survival", "--seeds", "-1", "--duration", "1"], "--seeds: expected seeds like"),
    (["bench", "tracker-mot", "--seeds", "-1", "--frames", "10"], "--seeds: expected seeds like"),
    (["bench", "tracker-mot", "--seeds", ",", "--frames", "10"], "--seeds: give at least one seed"),
    (["bench", "sidecar", "--seed", "1.5"], "--seed: '1.5' is not an integer"),  # had been taken as 1
    (["bench", "sidecar", "--seed", "-1"], "--seed: -1 is negative"),
    (["feed-tracks", "--seed", "-1", "--connect", "tcp/127.0.0.1:9"], "--seed: -1 is negative"),  # ran on, idle
    (["replay", "synthetic:mixed", "--seed", "-1"], "--seed: -1 is negative"),
    (["calibrate", "synthetic:mixed", "--seed", "-1", "--out", "{tmp}/c.yaml"], "--seed: -1 is negative"),
    (["bench", "track-survival", "--scenario", "nosuch", "--duration", "1"], "unknown scenario 'nosuch' (have: "),
    # no upper bound: tracebacks (LimitExceeded, int(inf), numpy's MemoryError) after seconds of work
    (["bench", "classifier", "--tracks", "1500", "--duration", "1"], "--tracks 1500 exceeds the classifier's"),
    (["bench", "classifier", "--rate", "inf", "--duration", "1"], "--rate: 'inf' is not a finite number"),
    (["bench", "classifier", "--duration", "inf"], "--duration: 'inf' is not a finite number"),
    (["bench", "pipeline", "--duration", "inf"], "--duration: 'inf' is not a finite number"),
    (["bench", "classifier", "--duration", "3601"], "--duration: 3601 is outside 1-3600"),
    # a flag kept as text (parse_float) is checked as float_option's are: nan had been "nan is outside 0.5-100"
    (["bench", "sidecar", "--rate", "nan"], "--rate: 'nan' is not a number"),
    (["bench", "sidecar", "--duration", "inf"], "--duration: 'inf' is not a finite number"),
    (["bench", "sidecar", "--tracks", "1500"], "--tracks 1500 exceeds the classifier's limits.max_objects 1000"),  # had waited 120 s
    (["status", "--listen-s", "0.01"], "--listen-s: 0.01 is outside 0.1-60"),
    (["bench", "replay", "--points", "10000000000", "--repeat", "1"], "--points: 10000000000 is more than"),
    (["bench", "replay", "--frames", "99999999999", "--repeat", "1"], "--frames: 99999999999 is more than"),
    # folders and files made only when the work was done (or by a program of a stack already started)
    (["bench", "pipeline", "--log-dir", "/proc/x", "--duration", "1"], "--log-dir: cannot create the folder /proc/x"),
    (["bench", "pipeline", "--log-dir", __file__, "--duration", "1"], "--log-dir: cannot create the folder"),
    (["domain-gap", "--out", "/proc/x", "--nuscenes", "{tmp}"], "--out: cannot create the folder /proc/x"),
    (["record", "--ros2", "/proc/x", "--connect", "tcp/127.0.0.1:9"], "--ros2: cannot create the folder /proc/x"),
    (["up", "--record-ros2", "/proc/x", "--run-dir", "{tmp}", "--duration", "1"],
     "--record-ros2: cannot create the folder /proc/x"),
    (["foxglove", "--record", "/proc/x.mcap", "--connect", "tcp/127.0.0.1:9"], "--record: cannot write /proc/x.mcap"),
    (["up", "--record-mcap", "/proc/x.mcap", "--run-dir", "{tmp}", "--duration", "1"],
     "--record-mcap: cannot write /proc/x.mcap"),
    # each alone refuses an existing path, not the one the other makes: the two recorders had raced for it
    (["up", "--record-mcap", "{tmp}/rec", "--record-ros2", "{tmp}/rec", "--run-dir", "{tmp}/run", "--duration", "1"],
     "--record-ros2: {tmp}/rec is where --record-mcap writes"),
    # an empty effect set had been taken as none: ideal scans added to (or making up) the training set
    (["train", "--out", "{tmp}/tr", "--effects", "random+"], "--effects: empty effect in ''"),
    (["train", "--out", "{tmp}/tr", "--effects", "ground,"], "--effects: empty effect in 'ground,'"),
    (["eval-detector", "--out", "{tmp}/ev", "--effects", ""], "--effects: empty effect"),
    # --ns names the stack where --name is not given: a bad one had been blamed on --name
    (["status", "--ns", "a/b", "--run-dir", "{tmp}/none"], "--ns: 'a/b' is not a stack name"),
    (["summary", "--ns", "a/b"], "--ns: 'a/b' is not a stack name"),
    (["eval-detector", "--out", "{tmp}/ev", "--name", "a/b"], "--name: expected a file-name stem"),
    (["eval-detector", "--out", "{tmp}/ev", "--name", ""], "--name: expected a file-name stem"),
    (["eval-detector", "--out", ""], "--out: empty path"),  # had written into the current folder
    # typer's Path had made "" the current folder, and the run wrote into it (exit 0)
    (["eval", "--out", "", "--duration", "1"], "--out: empty path"),
    (["eval-study", "--out", "", "--duration", "1"], "--out: empty path"),
    (["bench", "pipeline", "--log-dir", "", "--duration", "1"], "--log-dir: empty path"),
    (["sim", "generate", "mixed", "--out", "", "--duration", "1"], "--out: empty path"),  # taken as no --out
    (["sim", "export", "mixed", "", "--duration", "1"], "DATAROOT: empty path"),  # exported into the current folder
    # refused only after --out had been made: the empty folder was left behind
    (["eval", "--out", "{tmp}/ev", "--scenario", "nosuch"], "--scenario: unknown scenario 'nosuch'"),
    (["eval", "--out", "{tmp}/ev", "--nuscenes", "{tmp}"], "--nuscenes: "),
    # a bad value of a flag that sets a classifier key had been named by the key (alpha_default: …), not the flag
    (["eval", "--out", "{tmp}/ev", "--alpha", "-1"], "--alpha (alpha_default): Input should be greater than 0"),
    (["eval", "--out", "{tmp}/ev", "--velocity-threshold", "-1"], "--velocity-threshold (velocity_threshold): "),
    (["eval", "--out", "{tmp}/ev", "--min-speed", "-1"], "--min-speed (min_speed_mps): "),
    (["eval", "--out", "{tmp}/ev", "--window-size", "1"], "--window-size (window_size): "),
    (["eval", "--out", "{tmp}/ev", "--view-slide", "-1"], "--view-slide (view_slide_m_per_class."),
    (["eval", "--out", "{tmp}/ev", "--effective-n", "most"], "--effective-n (effective_n): "),
    (["eval", "--out", "{tmp}/ev", "--calibration", "often"], "--calibration (calibration): "),
    (["eval-study", "--out", "{tmp}/ev", "--seeds", "9-2"], "--seeds: expected seeds like 0-49"),
    (["domain-gap", "--out", "{tmp}/ev", "--nuscenes", "/nonexistent"], "--nuscenes: not a directory"),
    (["domain-gap", "--out", "{tmp}/ev", "--nuscenes", "{tmp}", "--seeds", "x"], "--seeds: expected seeds like"),
    (["bench", "pipeline", "--log-dir", "{tmp}/ev", "--objects", "10", "--churn", "20", "--duration", "1"],
     "--churn 20 exceeds --objects 10"),  # had run, reporting a churn no frame had
    # the PNG had been tried only after the scenario was made and the scan cast
    (["sim", "bev", "mixed", "--out", "/proc/x.png", "--frame", "999"], "--out: cannot write /proc/x.png"),
    # refused before the Zenoh session (retried for ever without a router), not after it
    (["replay", "synthetic:mixed", "--start", "100000", "--connect", "tcp/127.0.0.1:9"],
     "--start 100000 is past the end of synthetic:mixed"),
    (["replay", "synthetic:mixed", "--wait-subscriber", "nan", "--connect", "tcp/127.0.0.1:9"],
     "--wait-subscriber must be a number of seconds from 0 to 86400"),  # had waited for ever
    # flags that had been ignored without a word
    (["foxglove", "--overwrite", "--connect", "tcp/127.0.0.1:9"], "--overwrite: only with --record"),
    (["foxglove", "--number-if-exists", "--connect", "tcp/127.0.0.1:9"], "--number-if-exists: only with --record"),
    (["foxglove", "--record", "{tmp}/ev.mcap", "--overwrite", "--number-if-exists", "--connect", "tcp/127.0.0.1:9"],
     "give one of them"),
    (["up", "--foxglove-port", "9001", "--run-dir", "{tmp}", "--router-port", "0", "--duration", "1"],
     "--foxglove-port: only with --foxglove"),
    # the live ROS 2 side's flags, refused before a session would wait for a router
    (["ros2-in", "--middleware", "dds", "--connect", "tcp/127.0.0.1:9"], "--middleware: 'dds' is not one of"),
    # --no-pose had ignored a pose topic or type given beside it without a word
    (["ros2-in", "--no-pose", "--pose-topic", "/odom", "--connect", "tcp/127.0.0.1:9"],
     "--no-pose publishes every scan at the identity pose: give it or --pose-topic, not both"),
    (["ros2-in", "--no-pose", "--pose-type", "nav_msgs/msg/Odometry", "--connect", "tcp/127.0.0.1:9"],
     "give it or --pose-type, not both"),
    (["ros2-in", "--middleware", "rmw_zenoh", "--domain-id", "233", "--connect", "tcp/127.0.0.1:9"],
     "--domain-id: 233 is outside 0-232"),
    (["ros2-in", "--middleware", "rmw_zenoh", "--key-prefix", "robot1", "--connect", "tcp/127.0.0.1:9"],
     "--key-prefix: a bridge's namespace"),
    (["ros2-out", "--ros-connect", "localhost", "--connect", "tcp/127.0.0.1:9"], "endpoint 'localhost' must look like"),
    (["ros2-in", "--points-topic", "/points", "--objects-topic", "/objects", "--connect", "tcp/127.0.0.1:9"],
     "--objects-topic takes the vehicle's detections in place of scans"),
    (["ros2-in", "--objects-topic", "objects", "--connect", "tcp/127.0.0.1:9"],
     "--objects-topic: 'objects' is not a ROS 2 topic name"),
    (["ros2-in", "--points-topic", "", "--connect", "tcp/127.0.0.1:9"],  # had quietly read the default topic
     "--points-topic: '' is not a ROS 2 topic name"),
    # an empty chunk had passed the checks and ended in a traceback as a Zenoh key (--pose-topic: and then hung)
    (["ros2-in", "--pose-topic", "/a//b", "--connect", "tcp/127.0.0.1:9"], "--pose-topic: '/a//b' is not a ROS 2"),
    (["ros2-out", "--key-prefix", "a//b", "--connect", "tcp/127.0.0.1:9"], "--key-prefix: 'a//b' is not a Zenoh key"),
    (["ros2-out", "--key-prefix", "a/*", "--connect", "tcp/127.0.0.1:9"], "--key-prefix: 'a/*' is not a Zenoh key"),
    # with no SOURCE at all it had printed its help on stdout, exit 0, where one missing argument is exit 2
    (["replay"], "Missing argument 'source'"),
    (["status", "--listen-s", "1e9"], "--listen-s: 1e+09 is outside 0.1-60"),  # had listened for 31 years
    (["replay", "synthetic:mixed", "--wait-subscriber", "inf", "--connect", "tcp/127.0.0.1:9"],  # waited for ever
     "--wait-subscriber must be a number of seconds from 0 to 86400"),
    # an empty --run-dir had meant the default stack's (down stopped it) and the monitor's the current folder
    (["down", "--run-dir", ""], "--run-dir: empty path; give a folder"),
    (["status", "--run-dir", ""], "--run-dir: empty path; give a folder"),
    (["summary", "--run-dir", ""], "--run-dir: empty path; give a folder"),
    (["logs", "classifier", "--run-dir", ""], "--run-dir: empty path; give a folder"),
    (["up", "--run-dir", "", "--duration", "1"], "--run-dir: empty path; give a folder"),
    (["stack-monitor", "--run-dir", "", "--connect", "tcp/127.0.0.1:9"], "--run-dir: empty path; give a folder"),
    # an empty recording path: "--ros2:  exists", "--record:  is a folder"; with --number-if-exists a traceback
    (["record", "--ros2", "", "--connect", "tcp/127.0.0.1:9"], "--ros2: empty path; give a folder"),
    (["record", "--ros2", "", "--number-if-exists", "--connect", "tcp/127.0.0.1:9"], "--ros2: empty path"),
    (["foxglove", "--record", "", "--connect", "tcp/127.0.0.1:9"], "--record: empty path; give a file"),
    (["record", "--ros2", "{tmp}/bag", "--points-layout", "xyzi", "--connect", "tcp/127.0.0.1:9"],
     "--points-layout: 'xyzi' is not one of xyzirc, float32"),
    (["up", "--record-mcap", "", "--run-dir", "{tmp}", "--duration", "1"], "--record-mcap: empty path; give a file"),
    (["up", "--record-ros2", "", "--run-dir", "{tmp}", "--duration", "1"], "--record-ros2: empty path; give a folder"),
    # an empty --zenoh-config had meant none: the router started on its default endpoint, a service as a client
    (["router", "--zenoh-config", "", "--listen", "tcp/127.0.0.1:17461"], "--zenoh-config: empty path; give a file"),
    (["classifier", "--zenoh-config", "", "--connect", "tcp/127.0.0.1:9"], "--zenoh-config: empty path; give a file"),
    (["ros2-out", "--middleware", "rmw_zenoh", "--ros-distro", "Jazzy", "--connect", "tcp/127.0.0.1:9"],
     "--ros-distro: 'Jazzy' is not a ROS 2 distribution's name"),
    # an empty parameter file path had been "jitterguard: error: : not a file", naming neither flag nor problem
    (["classifier", "--config", "", "--connect", "tcp/127.0.0.1:9"], "--config: empty path; give a file"),
    (["detector", "--config", "", "--connect", "tcp/127.0.0.1:9"], "--config: empty path; give a file"),
    (["tracker", "--config", "", "--print-config"], "--config: empty path; give a file"),
    # what is there, not what is missing: a folder for a file had been "file not found", a file for a folder "no such
    # folder"; an empty path "." (the current folder); a bad value its flag's, not another's (probe, 7 Dec)
    (["detector", "--weights", "{tmp}", "--connect", "tcp/127.0.0.1:9"], "--weights: {tmp} is a folder, not a file"),
    (["tracker", "--zenoh-config", "{tmp}"], "--zenoh-config: {tmp} is a folder, not a file"),
    (["eval", "--out", "{tmp}/ev", "--nuscenes", __file__], f"--nuscenes: {__file__} is a file, not a folder"),
    (["calibrate", "synthetic:parking-street", "--out", ""], "--out: empty path; give a file name"),
    (["calibrate", "", "--out", "{tmp}/c.yaml"], "RECORDING: empty path"),
    (["sidecar", "--host", ""], "--host: empty; give an address"),
    (["bench", "sim", "--scenario", "nosuch"], "--scenario: unknown scenario 'nosuch'"),
    (["classifier", "--preset", "nosuch"], "--preset: unknown classifier preset 'nosuch'"),
])
def test_bad_input_is_refused_in_one_line_before_any_work(args, needle, tmp_path):
    cwd = tmp_path / "cwd"  # an empty --out that regressed to "the current folder" writes here, not into the repo
    cwd.mkdir()
    res = run([a.replace("{tmp}", str(tmp_path)) for a in args], cwd=cwd)
    needle = needle.replace("{tmp}", str(tmp_path))
    assert res.returncode == 2 and res.stderr.count("\n") == 1 and needle in res.stderr, res.stderr
    assert not (tmp_path / "ev").exists() and not (tmp_path / "supervisord.conf").exists()
    assert not any(cwd.iterdir())


@pytest.mark.parametrize("args", [["tracker"], ["router"]])
def test_a_config_files_endpoint_port_out_of_range_is_refused_as_the_flags_is(args, tmp_path):
    """``--connect tcp/127.0.0.1:99999`` is refused in one line; the same port in a ``--zenoh-config`` file had been
    retried for ever by a service, and printed by the router as a log line."""
    cfg = tmp_path / "z.json5"
    mode = "router" if args == ["router"] else "client"
    where = "listen" if mode == "router" else "connect"
    cfg.write_text(f'{{mode: "{mode}", {where}: {{endpoints: ["tcp/127.0.0.1:99999"]}}}}')
    res = run([*args, "--zenoh-config", str(cfg)])
    assert res.returncode == 2 and res.stderr.count("\n") == 1, res.stderr
    assert f"--zenoh-config {cfg}: endpoint 'tcp/127.0.0.1:99999': port '99999'" in res.stderr, res.stderr


def test_a_foxglove_port_in_use_is_named_and_no_recording_is_made_or_overwritten(tmp_path):
    """The MCAP had been opened before the port was bound: a port in use left an empty recording (which the next
    run refused as existing) or, with --overwrite, replaced an old one with nothing; and the message named no flag."""
    import socket

    from jitterguard.runtime import free_tcp_port

    port = free_tcp_port()
    old = tmp_path / "old.mcap"
    old.write_bytes(b"an earlier recording")
    with socket.create_server(("127.0.0.1", port)):
        for record, extra in ((tmp_path / "new.mcap", []), (old, ["--overwrite"])):
            res = run(["foxglove", "--port", str(port), "--record", str(record), "--connect", "tcp/127.0.0.1:9", *extra])
            assert res.returncode == 2 and res.stderr.count("\n") == 1, res.stderr
            assert f"--port: cannot serve on 127.0.0.1:{port}" in res.stderr, res.stderr
    assert not (tmp_path / "new.mcap").exists() and old.read_bytes() == b"an earlier recording"


def test_a_recorder_stopped_while_it_waits_for_its_router_leaves_no_bag(tmp_path):
    """The bag had been made before the Zenoh session: stopped during the wait for a router, the folder held a 0-byte
    MCAP and no ``metadata.yaml`` — no bag any reader opens — and the next run refused it as existing."""
    import signal
    import time

    from jitterguard.runtime import free_tcp_port

    proc = subprocess.Popen([sys.executable, "-m", "jitterguard.cli", "record", "--ros2", str(tmp_path / "bag"),
                             "--connect", f"tcp/127.0.0.1:{free_tcp_port()}"], stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 60
        waiting = ""
        while "retrying until the router" not in waiting and time.monotonic() < deadline:
            waiting += proc.stderr.readline()
        assert "retrying until the router" in waiting, waiting
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert not (tmp_path / "bag").exists()


def test_a_checkpoint_that_is_none_is_refused_before_the_data_are_prepared(tmp_path):
    """``train --resume`` over a damaged ``checkpoint.pt`` had cast every scan (minutes, cache folders in --out)
    before it said so."""
    (tmp_path / "checkpoint.pt").write_text("garbage")
    res = run(["train", "--out", str(tmp_path), "--resume", "--scenarios", "parking-street", "--train-seeds", "0",
               "--val-seeds", "1", "--frames-per-scenario", "1", "--batch-size", "1", "--epochs", "1", "--no-progress"])
    assert res.returncode == 2 and "--resume: " in res.stderr and "not a loadable checkpoint" in res.stderr, res.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["checkpoint.pt"]


@pytest.mark.parametrize(("args", "line"), [
    (["eval", "--bogus"], "jitterguard: error: No such option: --bogus"),
    (["bench", "classifier", "--rate"], "jitterguard: error: Option '--rate' requires an argument."
                                        " (see jitterguard bench classifier --help)"),
    (["sim", "generate", "nosuch", "--out"], "jitterguard: error: Option '--out' requires an argument."
                                             " (see jitterguard sim generate --help)"),
])
def test_the_parsers_own_refusals_have_the_prefix_of_every_other(args, line):
    """click's errors had been prefixed with the command path (``jitterguard eval: error:``) — or not, for a
    missing option value — while every refusal of jitterguard's own reads ``jitterguard: error:``."""
    res = run(args)
    assert res.returncode == 2 and res.stderr.count("\n") == 1 and res.stderr.startswith(line), res.stderr


def test_a_library_message_of_several_lines_is_joined_into_one(tmp_path):
    """A bag whose ``metadata.yaml`` is cut short: the YAML parser's message, with its caret display, had been
    printed as five lines."""
    bag = tmp_path / "bag"
    bag.mkdir()
    (bag / "metadata.yaml").write_text("foo: [")
    res = run(["calibrate", str(bag), "--out", str(tmp_path / "c.yaml")])
    assert res.returncode == 2 and res.stderr.count("\n") == 1, res.stderr
    assert f"{bag}: cannot open bag: Could not load YAML" in res.stderr and "line 1, column 7" in res.stderr


@pytest.mark.parametrize(("bands", "needle"), [("-5", "Input should be greater than 0"),
                                               ("nan", "Input should be a finite number"),
                                               ("a,b", "'a,b' is not a comma-separated list of distances in metres")])
def test_bad_range_bands_name_their_flag_in_one_line(bands, needle, tmp_path):
    """They had printed pydantic's whole dump, cut off in the middle of its URL."""
    res = run(["calibrate", "synthetic:mixed", "--level", "detections", "--out", str(tmp_path / "c.yaml"),
               f"--range-bands={bands}"])
    assert res.returncode == 2 and res.stderr.strip() == f"jitterguard: error: --range-bands: {needle}", res.stderr



@pytest.mark.parametrize("args", [
    ["eval-detector", "--out", "{out}", "--nuscenes", "{tmp}/nodata"],
    ["domain-gap", "--out", "{out}", "--nuscenes", "{tmp}/nodata"],
    ["adapt", "--out", "{out}", "--scans", "{tmp}/nodata"],
])
def test_a_run_refused_after_its_folder_was_made_leaves_no_empty_folder(args, tmp_path):
    """The folder is made before the slow checks (a run must not compute and then fail to write); refused after
    it — a folder that is no dataroot, scans it cannot read — it had stayed behind empty, parents and all."""
    (tmp_path / "nodata").mkdir()
    (tmp_path / "nodata" / "junk.txt").write_text("not a scan\n")
    kept = tmp_path / "kept"
    kept.mkdir()
    for out in (tmp_path / "new" / "deeper", kept):
        res = run([a.replace("{tmp}", str(tmp_path)).replace("{out}", str(out)) for a in args])
        assert res.returncode == 2 and res.stderr.count("\n") == 1, res.stderr
    assert not (tmp_path / "new").exists()  # both the folder and the parent it made
    assert kept.is_dir()  # a folder that was there before stays


def _ranged_float_flags() -> list[tuple[list[str], str]]:
    """(command path, flag) of every float flag of the app declared with a minimum or a maximum."""
    import typer

    from jitterguard.cli import app

    found: list[tuple[list[str], str]] = []

    def walk(cmd, path: list[str]) -> None:
        if hasattr(cmd, "commands"):
            for name, sub in cmd.commands.items():
                walk(sub, [*path, name])
            return
        for param in cmd.params:
            desc = getattr(param, "type_descriptor", None)
            if desc is not None and desc.is_ranged and desc.ranged_type_name == "float":
                found.append((path, param.opts[0]))

    walk(typer.main.get_command(app), [])
    return found


def test_nan_in_a_ranged_float_flag_is_called_not_a_number(capsys):
    """``--rate nan`` had been refused as breaking the other bound ("Input should be less than or equal to 1000"),
    and ``--tolerance inf`` (no maximum) accepted: every ranged float flag, found in the app, names itself and says
    what is wrong, one line, exit 2, before any work."""
    from jitterguard.cli import main

    flags = _ranged_float_flags()
    assert {("bench classifier", "--rate"), ("up", "--duration"), ("export-onnx", "--tolerance")} <= {
        (" ".join(path), flag) for path, flag in flags}, flags
    wrong = []
    for path, flag in flags:
        for value, why in (("nan", "is not a number"), ("-inf", "is not a finite number")):
            with pytest.raises(SystemExit) as exc:
                main([*path, flag, value])
            err = capsys.readouterr().err
            if exc.value.code != 2 or err != f"jitterguard: error: {flag}: {value!r} {why}\n":
                wrong.append((path, flag, exc.value.code, err))
    assert not wrong, wrong
