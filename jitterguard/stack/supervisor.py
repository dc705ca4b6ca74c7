"""The stack under supervisord: which programs run, and the config file that says so.

Pure functions build the program list and render ``supervisord.conf``; :mod:`jitterguard.stack.cli` writes it
into a run directory and drives ``supervisord`` (:mod:`.control`). Every program is this same Python's
``-m jitterguard.cli`` so the stack runs from whatever environment ``jitterguard up`` was started in.

Every value that reaches the file was checked by :mod:`.validate` (no control characters, no comment starts)
and is written with ``%`` doubled, so supervisord reads back exactly the argument the user gave.
"""

from __future__ import annotations

import importlib.util
import shlex
import sys
from dataclasses import dataclass, field
from pathlib import Path

from ..runtime.exit_codes import EXIT_BAD_INPUT
from ..services.classifier.config_writes import api_token_from_env
from .validate import check_text, supervisor_escape


@dataclass(frozen=True)
class Program:
    """One supervised process. Lower ``priority`` starts first (the router is 10).

    A ``deferred`` program is not started with the others: ``jitterguard up`` starts it once the pipeline runs
    (first objects, or every other program RUNNING). Programs off the path to the first objects (the sidecar,
    the monitor) would otherwise spend the seconds of CPU that the pipeline needs to come up on a small machine.
    """

    name: str
    args: tuple[str, ...]
    priority: int = 50
    startsecs: int = 1
    deferred: bool = False
    autorestart: str = "true"  # supervisord's: true, or unexpected (an exit with one of ``exitcodes`` stays down)
    exitcodes: tuple[int, ...] = (0,)
    events: str | None = None
    """A supervisord event listener subscribed to these events (``[eventlistener:NAME]``): its stdout is supervisord's
    protocol, so only its stderr is logged."""


@dataclass(frozen=True)
class StackSpec:
    """What ``jitterguard up`` runs; defaults give the embedded demo on one host."""

    ns: str = "default"
    name: str = "default"  # the stack's name: its run directory, and what down/status/summary/logs --name pick
    router_port: int = 7447
    sidecar_host: str = "127.0.0.1"
    sidecar_port: int = 8000
    source: str | None = None  # replay SOURCE (absolute path or synthetic:NAME); None = the default scenario
    input: str = "auto"  # auto | points | detections | tracks
    replay_args: tuple[str, ...] = ()  # replay options (ReplayOptions.argv), paths absolute
    run_dir: str = ""  # absolute; where config, socket, logs and summary.json live
    sidecar: bool = True
    extra_env: dict[str, str] = field(default_factory=dict)
    foxglove: bool = False  # the Foxglove WebSocket server (loopback, foxglove_port)
    foxglove_port: int = 8765
    record_mcap: str | None = None  # absolute path: the Foxglove channels recorded to MCAP
    record_ros2: str | None = None  # absolute path: a rosbag2 for Autoware
    service_configs: dict[str, str] = field(default_factory=dict)  # service → its param.yaml (absolute path)
    # live ROS 2 in the replay's place: this topic in (PointCloud2; DetectedObjects with input "detections"),
    # TrackedObjects out (the name is older than DetectedObjects' way in; saved specs keep it)
    ros2_points: str | None = None
    ros2_args: tuple[str, ...] = ()  # the ROS 2 side's middleware flags, for both ros2-in and ros2-out

    @property
    def endpoint(self) -> str:
        return f"tcp/127.0.0.1:{self.router_port}"


def has_area(module: str) -> bool:
    """Whether an optional part of jitterguard is present in this build."""
    try:
        return importlib.util.find_spec(module) is not None
    except ModuleNotFoundError:
        return False


DEFAULT_SOURCE = "synthetic:mixed"
DEFAULT_SCENARIO_S = 60.0
"""The default scenario's length: the loop boundary (a restart, see ``replay --loop``) comes once a minute, not
every 20 s. Longer costs start-up time: the replay simulates the whole scenario before its first frame (about
0.04 s per scenario second on one loaded core), and the time to the first objects should stay near 5 s."""


def _cmd(*args: str) -> tuple[str, ...]:
    return (sys.executable, "-m", "jitterguard.cli", *args)


def input_mode(spec: StackSpec, source_kind: str | None = None) -> str:
    """The input level the stack runs at: ``spec.input``, or for ``auto`` the source's own level if it has one
    (a bag of DetectedObjects), else points when the detector is present, else detections, else tracks."""
    if spec.input != "auto":
        return spec.input
    if source_kind == "detections":
        return "detections"
    have_tracker = has_area("jitterguard.services.tracker.service")
    have_replay = all(has_area(m) for m in ("jitterguard.services.replay.cli", "jitterguard.sim.world",
                                             "jitterguard.sim.detection_model"))
    if has_area("jitterguard.services.detector.service"):
        return "points"
    return "detections" if (have_tracker and have_replay) else "tracks"


CONSUMER_WAIT_S = 120.0
"""How long the stack's replay waits for the pipeline's first stage to say it is ready before replaying anyway."""


def programs(spec: StackSpec) -> list[Program]:
    """The programs of the stack, router first, consumers before producers."""
    common = ("--ns", spec.ns, "--connect", spec.endpoint)

    def own(service: str) -> tuple[str, ...]:
        path = spec.service_configs.get(service)
        return ("--config", path) if path else ()

    progs = [
        Program("router", _cmd("router", "--listen", spec.endpoint), priority=10),
        # with no JG_API_TOKEN, writes over Zenoh are as open as the tokenless loopback sidecar (deployment.md)
        Program("classifier", _cmd("classifier", *common, *own("classifier"), *(
            () if api_token_from_env() else ("--open-config-writes",))), priority=20),
    ]
    have_tracker = has_area("jitterguard.services.tracker.service")
    have_detector = has_area("jitterguard.services.detector.service")
    mode = input_mode(spec)
    if mode in ("points", "detections") and have_tracker:
        progs.append(Program("tracker", _cmd("tracker", *common, *own("tracker")), priority=30))
    if mode == "points" and have_detector:
        progs.append(Program("detector", _cmd("detector", *common, *own("detector")), priority=35))
    if spec.sidecar and has_area("jitterguard.services.sidecar.cli"):
        progs.append(Program("sidecar", _cmd("sidecar", *common, "--host", spec.sidecar_host,
                                             "--port", str(spec.sidecar_port)), priority=40, deferred=True))
    progs += bridge_programs(spec, common)
    if spec.ros2_points:  # a vehicle's ROS 2 side: a bridge as a client of the router, or nodes on rmw_zenoh
        progs.append(Program("ros2-out", _cmd("ros2-out", *common, *spec.ros2_args), priority=45))
        topic_flag = "--objects-topic" if mode == "detections" else "--points-topic"
        progs.append(Program("ros2-in", _cmd("ros2-in", *common, *spec.ros2_args, topic_flag, spec.ros2_points),
                             priority=60, startsecs=2))
    elif mode == "tracks":
        progs.append(Program("replay", _cmd("feed-tracks", *common, "--loop"), priority=60, startsecs=2))
    else:
        source = spec.source or DEFAULT_SOURCE
        # replay_args come from `up`, which probed the source and says its level (a bag's topic decides its own);
        # the built-in scenario gets its defaults here
        args = list(spec.replay_args)
        if spec.source is None and "--duration" not in args:
            args += ["--duration", f"{DEFAULT_SCENARIO_S:g}"]
        if spec.source is None and mode == "detections" and "--level" not in args:
            args += ["--level", "detections"]
        # the stack's replay stands in for a live sensor: wall-clock stamps, so that when supervisord restarts
        # it the tracker sees a restarted source going on in time, not a recording rewound (see stream_order);
        # each loop pass is such a restart too
        # the pipeline's first stage, not any subscriber (a Foxglove bridge or recorder comes up first), before
        # the first frame: the detector's start (torch, weights) takes seconds
        consumer = {"points": "detector" if have_detector else None,
                    "detections": "tracker" if have_tracker else None}.get(mode)
        if consumer is not None:
            args += ["--wait-for", consumer, "--wait-subscriber", f"{CONSUMER_WAIT_S:g}"]
        # a stop on bad input (--on-error stop: exit 65) is deliberate: not restarted, or it meets the same frame
        # again and again; any other exit (0 too: a looping replay does not end by itself) is restarted as before
        progs.append(Program("replay", _cmd("replay", source, *common, "--loop", "--stamps", "wall", *args),
                             priority=60, startsecs=2, autorestart="unexpected", exitcodes=(EXIT_BAD_INPUT,)))
    # the run's bookkeeping: sums every service's heartbeat counters across restarts into summary.json; it stops
    # last (supervisord stops in reverse priority), so it hears the final heartbeats; started once the pipeline
    # runs (a process's counters are cumulative, so its first heartbeat heard carries everything before it)
    progs.append(Program("monitor", _cmd("stack-monitor", *common, "--run-dir", spec.run_dir),
                         priority=5, deferred=True))
    # who ends the monitor when it is the one stopped (SIGSTOP): a light event listener, no Zenoh; the monitor in
    # turn ends it stopped, as any program it never hears from
    progs.append(Program("monitor-watch", (sys.executable, "-m", "jitterguard.stack.watch", "--run-dir", spec.run_dir),
                         priority=1, events="TICK_5"))
    return progs


def bridge_programs(spec: StackSpec, common: tuple[str, ...]) -> list[Program]:
    """The optional viewers/recorders beside the pipeline: ``foxglove`` (server and/or MCAP) and ``record`` (ROS 2
    bag). A recorder that supervisord restarts writes ``NAME.1``, ``NAME.2``, ... rather than over its last run."""
    progs = []
    if spec.foxglove or spec.record_mcap:
        args = [*common, "--port", str(spec.foxglove_port)]
        if not spec.foxglove:
            args.append("--no-server")
        if spec.record_mcap:
            args += ["--record", spec.record_mcap, "--number-if-exists"]
        progs.append(Program("foxglove", _cmd("foxglove", *args), priority=45))
    if spec.record_ros2:
        progs.append(Program("record", _cmd("record", *common, "--ros2", spec.record_ros2, "--number-if-exists"),
                             priority=45))
    return progs


def render_config(spec: StackSpec, run_dir: Path, progs: list[Program], *, nodaemon: bool) -> str:
    """supervisord.conf for ``progs``: autorestart (a program's own, with its ``exitcodes``), start retries,
    process-group stops, rotated logs.

    Raises ``ValueError`` if a value could change the file's structure (:func:`.validate.check_text`; ``up``
    checks its arguments earlier, with friendlier messages); every ``%`` is doubled for supervisord.
    """
    run_dir = run_dir.resolve()
    logs = run_dir / "logs"

    def v(value: object, what: str) -> str:
        return supervisor_escape(check_text(str(value), what))

    # the classifier keeps config writes and its online calibration in the run directory, so a restart of it (or
    # of the stack) keeps them
    env = ",".join(f'{k}="{v(val, "environment")}"' for k, val in {
        "PYTHONUNBUFFERED": "1", "JG_CONFIG_STORE": str(run_dir / "classifier-config.json"),
        "JG_CALIBRATION_STORE": str(run_dir / "classifier-calibration.npz"), **spec.extra_env}.items())
    lines = [
        "; generated by `jitterguard up`; see deploy/supervisord.conf for a hand-editable system config",
        "[unix_http_server]",
        f"file={v(run_dir / 'supervisor.sock', 'run dir')}",
        "chmod=0700",
        "",
        "[supervisord]",
        f"logfile={v(logs / 'supervisord.log', 'run dir')}",
        "logfile_maxbytes=10MB",
        "logfile_backups=3",
        f"pidfile={v(run_dir / 'supervisord.pid', 'run dir')}",
        f"nodaemon={'true' if nodaemon else 'false'}",
        "silent=true",
        f"directory={v(run_dir, 'run dir')}",
        f"environment={env}",
        "",
        "[rpcinterface:supervisor]",
        "supervisor.rpcinterface_factory = supervisor.rpcinterface:make_main_rpcinterface",
        "",
        "[supervisorctl]",
        f"serverurl=unix://{v(run_dir / 'supervisor.sock', 'run dir')}",
        "",
    ]
    for p in progs:
        section = "eventlistener" if p.events else "program"
        lines += [
            f"[{section}:{v(p.name, 'program name')}]",
            f"command={v(shlex.join(p.args), p.name + ' command')}",
            f"priority={p.priority}",
            f"autostart={'false' if p.deferred else 'true'}",
            f"autorestart={p.autorestart}",
            f"exitcodes={','.join(str(c) for c in p.exitcodes)}",
            f"startsecs={p.startsecs}",
            "startretries=10",
            "stopsignal=TERM",
            "stopwaitsecs=10",
            "stopasgroup=true",
            "killasgroup=true",
            *((f"events={v(p.events, 'events')}", "stdout_logfile=NONE",
               f"stderr_logfile={v(logs / (p.name + '.log'), 'run dir')}", "stderr_logfile_maxbytes=10MB",
               "stderr_logfile_backups=3") if p.events else
              ("redirect_stderr=true", f"stdout_logfile={v(logs / (p.name + '.log'), 'run dir')}",
               "stdout_logfile_maxbytes=10MB", "stdout_logfile_backups=3")),
            "",
        ]
    return "\n".join(lines)
