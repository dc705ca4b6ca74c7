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


def test_the_units_run_scans_through_the_detector_to_classified_objects(tmp_path):
    assert "jitterguard-detector.service" in wanted_units()
    router, http = free_tcp_port(), free_tcp_port()
    shipped = environment_file(SYSTEMD / "jitterguard.env")
    env = {k: v.replace("tcp/127.0.0.1:7447", f"tcp/127.0.0.1:{router}").replace("/var/lib/jitterguard", str(tmp_path))
           .replace("--port 8000", f"--port {http}") for k, v in shipped.items()}
    env["JG_NS"] = f"systemd{os.getpid()}"
    env["JG_REPLAY_ARGS"] += " --duration 30"  # the scenario ray-cast once, shorter than the default's 60 s
    venv_bin = str(Path(sys.executable).parent)
    base = {k: v for k, v in os.environ.items() if not k.startswith(("JG_", "SUPERVISOR_", "NOTIFY_SOCKET"))}
    procs: dict[str, subprocess.Popen] = {}
    logs = {}
    try:
        # the router first (every unit is After= it), then the rest in the target's order
        for unit in sorted(wanted_units(), key=lambda u: u != "jitterguard-router.service"):
            cp = configparser.ConfigParser(interpolation=None, strict=False)
            cp.read(SYSTEMD / unit)
            svc = cp["Service"]
            assert svc["EnvironmentFile"] == "/etc/jitterguard/jitterguard.env"
            argv = expand(svc["ExecStart"], env)
            assert argv[0] == "/opt/jitterguard/venv/bin/jitterguard"
            argv[0] = f"{venv_bin}/jitterguard"
            name = unit.removeprefix("jitterguard-").removesuffix(".service")
            logs[name] = tmp_path / f"{name}.log"
            procs[name] = subprocess.Popen(argv, env={**base, **env}, cwd=tmp_path, stdout=logs[name].open("wb"),
                                           stderr=subprocess.STDOUT, start_new_session=True)
        url = f"http://127.0.0.1:{http}"

        def flowing() -> bool:
            body = _readyz(url)
            if not body or not body.get("ready"):
                return False
            seen = body["services"]
            return all((seen.get(s, {}).get("last_seq") or 0) > 10 for s in ("detector", "tracker", "classifier"))

        def tail() -> str:
            return "\n".join(f"--- {n} (rc {p.poll()})\n" + logs[n].read_text(errors="replace")[-1500:]
                             for n, p in procs.items())

        assert wait_until(flowing, timeout=TIMEOUT_S, period=1.0), tail()
        state = httpx.get(f"{url}/v1/state", timeout=5.0).json()
        assert state["tracks"] and sum(state["counts"].values()) > 0, state  # classified objects from detected scans
        assert all(p.poll() is None for p in procs.values()), tail()
    finally:
        for p in procs.values():
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGTERM)
        for p in procs.values():
            try:
                p.wait(timeout=15)
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait(timeout=15)
