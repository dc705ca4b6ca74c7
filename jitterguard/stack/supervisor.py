"""The stack under supervisord: which programs run, and the config file that says so.

Pure functions build the program list and render ``supervisord.conf``; :mod:`jitterguard.stack.cli` writes it
into a run directory and drives ``supervisord`` / ``supervisorctl``. Every program is this same Python's
``-m jitterguard.cli`` so the stack runs from whatever environment ``jitterguard up`` was started in.
"""

from __future__ import annotations

import importlib.util
import os
import shlex
import sys
from dataclasses import dataclass, field
from pathlib import Path


@dataclass(frozen=True)
class Program:
    """One supervised process. Lower ``priority`` starts first (the router is 10)."""

    name: str
    args: tuple[str, ...]
    priority: int = 50
    startsecs: int = 1


@dataclass(frozen=True)
class StackSpec:
    """What ``jitterguard up`` runs; defaults give the embedded demo on one host."""

    ns: str = "default"
    router_port: int = 7447
    sidecar_host: str = "127.0.0.1"
    sidecar_port: int = 8000
    source: str | None = None  # replay SOURCE; None = the built-in synthetic scenario
    input: str = "auto"  # auto | points | detections | tracks
    sidecar: bool = True
    extra_env: dict[str, str] = field(default_factory=dict)
    foxglove: bool = False  # the Foxglove WebSocket server (loopback, foxglove_port)
    foxglove_port: int = 8765
    record_mcap: str | None = None  # absolute path: the Foxglove channels recorded to MCAP
    record_ros2: str | None = None  # absolute path: a rosbag2 for Autoware

    @property
    def endpoint(self) -> str:
        return f"tcp/127.0.0.1:{self.router_port}"


def has_area(module: str) -> bool:
    """Whether an optional part of jitterguard is present in this build."""
    try:
        return importlib.util.find_spec(module) is not None
    except ModuleNotFoundError:
        return False


def _cmd(*args: str) -> tuple[str, ...]:
    return (sys.executable, "-m", "jitterguard.cli", *args)


def programs(spec: StackSpec) -> list[Program]:
    """The programs of the stack, router first, consumers before producers."""
    common = ("--ns", spec.ns, "--connect", spec.endpoint)
    progs = [
        Program("router", _cmd("router", "--listen", spec.endpoint), priority=10),
        # with no JG_API_TOKEN, writes over Zenoh are as open as the tokenless loopback sidecar (deployment.md)
        Program("classifier", _cmd("classifier", *common, *(() if os.environ.get("JG_API_TOKEN") else
                                                             ("--open-config-writes",))), priority=20),
    ]
    have_tracker = has_area("jitterguard.services.tracker.service")
    have_replay = all(has_area(m) for m in ("jitterguard.services.replay.cli", "jitterguard.sim.world",
                                             "jitterguard.sim.detection_model"))
    have_detector = has_area("jitterguard.services.detector.service")
    mode = spec.input
    if mode == "auto":
        mode = "points" if have_detector else ("detections" if (have_tracker and have_replay) else "tracks")
    if mode in ("points", "detections") and have_tracker:
        progs.append(Program("tracker", _cmd("tracker", *common), priority=30))
    if mode == "points" and have_detector:
        progs.append(Program("detector", _cmd("detector", *common), priority=35))
    if spec.sidecar and has_area("jitterguard.services.sidecar.cli"):
        progs.append(Program("sidecar", _cmd("sidecar", *common, "--host", spec.sidecar_host,
                                             "--port", str(spec.sidecar_port)), priority=40))
    progs += bridge_programs(spec, common)
    if mode == "tracks":
        progs.append(Program("replay", _cmd("feed-tracks", *common, "--loop"), priority=60, startsecs=2))
    else:
        source = spec.source or "synthetic:mixed"
        flags = ("--level", "detections") if mode == "detections" else ()
        # the stack's replay stands in for a live sensor: wall-clock stamps, so that when supervisord restarts
        # it the tracker sees a restarted source going on in time, not a recording rewound (see stream_order)
        progs.append(Program("replay", _cmd("replay", source, *common, "--loop", "--stamps", "wall", *flags),
                             priority=60, startsecs=2))
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
    """supervisord.conf for ``progs``: autorestart, start retries, process-group stops, rotated logs."""
    run_dir = run_dir.resolve()
    logs = run_dir / "logs"
    # the classifier keeps config writes in the run directory, so a restart of it (or of the stack) keeps them
    env = ",".join(f'{k}="{v}"' for k, v in {"PYTHONUNBUFFERED": "1",
                                              "JG_CONFIG_STORE": str(run_dir / "classifier-config.json"),
                                              **spec.extra_env}.items())
    lines = [
        "; generated by `jitterguard up`; see deploy/supervisord.conf for a hand-editable system config",
        "[unix_http_server]",
        f"file={run_dir / 'supervisor.sock'}",
        "",
        "[supervisord]",
        f"logfile={logs / 'supervisord.log'}",
        "logfile_maxbytes=10MB",
        "logfile_backups=3",
        f"pidfile={run_dir / 'supervisord.pid'}",
        f"nodaemon={'true' if nodaemon else 'false'}",
        f"directory={run_dir}",
        f"environment={env}",
        "",
        "[rpcinterface:supervisor]",
        "supervisor.rpcinterface_factory = supervisor.rpcinterface:make_main_rpcinterface",
        "",
        "[supervisorctl]",
        f"serverurl=unix://{run_dir / 'supervisor.sock'}",
        "",
    ]
    for p in progs:
        lines += [
            f"[program:{p.name}]",
            f"command={shlex.join(p.args)}",
            f"priority={p.priority}",
            "autostart=true",
            "autorestart=true",
            f"startsecs={p.startsecs}",
            "startretries=10",
            "stopsignal=TERM",
            "stopwaitsecs=10",
            "stopasgroup=true",
            "killasgroup=true",
            "redirect_stderr=true",
            f"stdout_logfile={logs / (p.name + '.log')}",
            "stdout_logfile_maxbytes=10MB",
            "stdout_logfile_backups=3",
            "",
        ]
    return "\n".join(lines)
