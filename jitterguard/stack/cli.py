"""``jitterguard up / down / status / logs``: the stack under supervisord, from one command."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Annotated

import typer

from ..cli_common import NsOpt, fail
from .status import collect, load_spec, render_table, save_spec
from .supervisor import StackSpec, programs, render_config

RunDirOpt = Annotated[str | None, typer.Option("--run-dir", envvar="JG_RUN_DIR", help="Where config, socket and logs live.")]


def default_run_dir(ns: str) -> Path:
    base = os.environ.get("XDG_RUNTIME_DIR") or str(Path.home() / ".cache")
    return Path(base) / "jitterguard" / ns


def _ctl(run_dir: Path, *args: str, check: bool = False) -> subprocess.CompletedProcess:
    conf = run_dir / "supervisord.conf"
    if not conf.is_file():
        fail(f"no stack found in {run_dir} (start one with `jitterguard up`)")
    return subprocess.run([sys.executable, "-m", "supervisor.supervisorctl", "-c", str(conf), *args],
                          capture_output=True, text=True, check=check)


def _wait_for_objects(ns: str, endpoint: str, timeout: float) -> float | None:
    """Seconds until the first classified ``objects`` arrives, or None."""
    from ..runtime import ZenohOptions, build_config, open_session
    from ..schemas import keys

    got: list[float] = []
    t0 = time.monotonic()
    cfg = build_config(ZenohOptions(ns=ns, connect=(endpoint,)))
    try:  # a client of the stack's router, which supervisord may still be starting
        session = open_session(cfg, timeout_s=timeout)
    except Exception:
        return None
    with session:
        sub = session.declare_subscriber(keys.objects(ns), lambda s: got.append(time.monotonic()))
        while not got and time.monotonic() - t0 < timeout:
            time.sleep(0.05)
        sub.undeclare()
    return (got[0] - t0) if got else None


def _recording_path(value: str | None, flag: str) -> str | None:
    """An absolute path for a recording (supervisord runs programs in the run dir) that does not exist yet."""
    if value is None:
        return None
    p = Path(value).expanduser().resolve()
    if p.exists():
        fail(f"{flag}: {value} exists")
    if not p.parent.is_dir():
        fail(f"{flag}: no folder {p.parent}")
    return str(p)


def register(app: typer.Typer, bench_app: typer.Typer) -> None:
    @app.command("up")
    def up_cmd(
        source: Annotated[str | None, typer.Argument(help="Replay source (default: the built-in synthetic scenario).")] = None,
        ns: NsOpt = "default",
        detach: Annotated[bool, typer.Option("-d", "--detach", help="Start in the background and return.")] = False,
        input_level: Annotated[str, typer.Option("--input", help="auto, points, detections or tracks.")] = "auto",
        router_port: Annotated[int, typer.Option("--router-port", min=1, max=65535)] = 7447,
        host: Annotated[str, typer.Option("--host", help="Sidecar bind address.")] = "127.0.0.1",
        port: Annotated[int, typer.Option("--port", min=1, max=65535, help="Sidecar port.")] = 8000,
        run_dir: RunDirOpt = None,
        no_sidecar: Annotated[bool, typer.Option("--no-sidecar", help="Leave the HTTP sidecar out.")] = False,
        duration: Annotated[float | None, typer.Option("--duration", min=1.0, help="Stop after this many seconds.")] = None,
        foxglove: Annotated[bool, typer.Option("--foxglove", help="Serve the pipeline to Foxglove (ws://127.0.0.1:PORT).")] = False,
        foxglove_port: Annotated[int, typer.Option("--foxglove-port", min=1, max=65535)] = 8765,
        record_mcap: Annotated[str | None, typer.Option("--record-mcap", help="Record the Foxglove channels to this MCAP file.")] = None,
        record_ros2: Annotated[str | None, typer.Option("--record-ros2", help="Record a ROS 2 bag for Autoware into this new folder.")] = None,
    ) -> None:
        """Start router, replay, (detector,) tracker, classifier and sidecar under supervisord."""
        if input_level not in ("auto", "points", "detections", "tracks"):
            fail(f"--input: expected auto, points, detections or tracks, got {input_level!r}")
        rd = Path(run_dir) if run_dir else default_run_dir(ns)
        if (rd / "supervisor.sock").exists() and _ctl(rd, "pid").returncode == 0:
            fail(f"a stack is already running from {rd} (stop it with `jitterguard down --ns {ns}`)")
        (rd / "logs").mkdir(parents=True, exist_ok=True)
        mcap_path, bag_path = _recording_path(record_mcap, "--record-mcap"), _recording_path(record_ros2, "--record-ros2")
        spec = StackSpec(ns=ns, router_port=router_port, sidecar_host=host, sidecar_port=port, source=source,
                         input=input_level, sidecar=not no_sidecar, foxglove=foxglove, foxglove_port=foxglove_port,
                         record_mcap=mcap_path, record_ros2=bag_path)
        progs = programs(spec)
        conf = rd / "supervisord.conf"
        conf.write_text(render_config(spec, rd, progs, nodaemon=not detach))
        save_spec(rd, spec)
        cmd = [sys.executable, "-m", "supervisor.supervisord", "-c", str(conf)]
        names = ", ".join(p.name for p in progs)
        if detach:
            subprocess.run(cmd, check=True)
            print(f"jitterguard: started {names} (run dir {rd})")
            if any(p.name == "sidecar" for p in progs):
                print(f"sidecar: http://{host}:{port}/")
            return
        proc = subprocess.Popen(cmd)
        stop = {"flag": False}

        def _stop(*_: object) -> None:
            stop["flag"] = True

        signal.signal(signal.SIGINT, _stop)
        signal.signal(signal.SIGTERM, _stop)
        print(f"jitterguard: starting {names} (logs in {rd / 'logs'})", flush=True)
        first = _wait_for_objects(ns, spec.endpoint, timeout=60.0)
        if first is None:
            print("jitterguard: no classified objects within 60 s; see `jitterguard logs classifier`", file=sys.stderr)
        else:
            print(f"jitterguard: first classified objects after {first:.1f} s", flush=True)
        if any(p.name == "sidecar" for p in progs):
            print(f"sidecar: http://{host}:{port}/  (Ctrl-C stops the stack)", flush=True)
        if foxglove:
            print(f"foxglove: ws://127.0.0.1:{foxglove_port}  (layout: deploy/foxglove/jitterguard.json)", flush=True)
        t_end = time.monotonic() + duration if duration else None
        while not stop["flag"] and proc.poll() is None and (t_end is None or time.monotonic() < t_end):
            time.sleep(0.2)
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            proc.wait(timeout=60)
        print("jitterguard: stack stopped")
        if first is None:
            raise SystemExit(1)

    @app.command("down")
    def down_cmd(ns: NsOpt = "default", run_dir: RunDirOpt = None) -> None:
        """Stop a stack started with `jitterguard up -d`."""
        rd = Path(run_dir) if run_dir else default_run_dir(ns)
        res = _ctl(rd, "shutdown")
        print(res.stdout.strip() or res.stderr.strip())

    @app.command("status")
    def status_cmd(
        ns: NsOpt = "default",
        run_dir: RunDirOpt = None,
        as_json: Annotated[bool, typer.Option("--json", help="Machine-readable output.")] = False,
        listen: Annotated[float, typer.Option("--listen-s", min=0.1, help="Seconds to listen for heartbeats.")] = 1.5,
    ) -> None:
        """Per service: supervisor state, pid, uptime, liveliness on Zenoh and last frame seq."""
        rd = Path(run_dir) if run_dir else default_run_dir(ns)
        res = _ctl(rd, "status")
        if res.returncode not in (0, 3):  # 3: some program is not RUNNING
            print(res.stdout.rstrip() or res.stderr.rstrip(), file=sys.stderr)
            raise SystemExit(1)
        spec = load_spec(rd)
        rows = collect(res.stdout, spec, listen_s=listen)
        if as_json:
            import json

            print(json.dumps({"ns": spec.ns if spec else ns, "endpoint": spec.endpoint if spec else None,
                              "run_dir": str(rd), "services": [r.as_dict() for r in rows]}, indent=2))
        else:
            render_table(rows, spec, rd)
        if res.returncode == 3:
            raise SystemExit(3)

    @app.command("logs")
    def logs_cmd(
        service: Annotated[str, typer.Argument(help="router, replay, detector, tracker, classifier or sidecar.")],
        ns: NsOpt = "default",
        run_dir: RunDirOpt = None,
        lines: Annotated[int, typer.Option("-n", "--lines", min=1)] = 50,
    ) -> None:
        """Show the last lines of one service's log."""
        rd = Path(run_dir) if run_dir else default_run_dir(ns)
        log = rd / "logs" / f"{service}.log"
        if not log.is_file():
            fail(f"no log for {service!r} in {rd / 'logs'}")
        print("\n".join(log.read_text(errors="replace").splitlines()[-lines:]))
