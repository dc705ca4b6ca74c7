"""The sidecar's address that `jitterguard up` prints answers at once (a real stack under supervisord).

The sidecar starts deferred (at the first objects in the foreground, once the rest runs with ``-d``) and takes
seconds to import and open its session. `up` had printed ``sidecar: http://…/`` when it started it, so an
operator (or a script: ``jitterguard up -d && curl …``) who followed it at once got "connection refused".
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import tempfile

import httpx
import pytest

from jitterguard.runtime import free_tcp_port

pytestmark = pytest.mark.integration


def _up_args(name: str, router_port: int, port: int) -> list[str]:
    return [sys.executable, "-m", "jitterguard.cli", "up", "synthetic:parking-street", "--input", "detections",
            "--scenario-duration", "10", "--name", name, "--ns", f"{name}{os.getpid()}",
            "--router-port", str(router_port), "--port", str(port)]


def test_the_printed_sidecar_address_answers_at_once(tmp_path):
    env = {**os.environ, "XDG_RUNTIME_DIR": str(tmp_path / "xdg")}
    router_port, port = free_tcp_port(), free_tcp_port()
    url = f"http://127.0.0.1:{port}/"
    args = _up_args("addr", router_port, port)

    down = [sys.executable, "-m", "jitterguard.cli", "down", "--name", "addr"]
    try:
        # foreground: the line comes once the sidecar listens
        proc = subprocess.Popen([*args, "--duration", "60"], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                text=True, env=env)
        seen: list[str] = []
        try:
            assert proc.stdout is not None
            for line in proc.stdout:
                seen.append(line.rstrip())
                if line.startswith("sidecar: "):
                    assert line.split()[1] == url
                    assert httpx.get(url + "healthz", timeout=5.0).status_code == 200, seen
                    break
            else:
                pytest.fail("no sidecar line: " + "\n".join(seen))
        finally:
            proc.send_signal(signal.SIGINT)  # `up` stops its stack and prints the summary
            rest = proc.communicate(timeout=120)[0]
        assert proc.returncode == 0, "\n".join(seen) + rest

        # detached: `up -d` returns once the sidecar answers; this time with the user's classifier and tracker
        # param files, which their programs run with (the classifier's window as the sidecar serves it)
        cls, trk = tmp_path / "classifier.param.yaml", tmp_path / "tracker.param.yaml"
        cls.write_text("/**:\n  ros__parameters:\n    window_size: 7\n")
        trk.write_text("confirm_hits: 2\n")
        res = subprocess.run([*args, "-d", "--classifier-config", str(cls), "--tracker-config", str(trk)],
                             capture_output=True, text=True, env=env, timeout=120)
        assert res.returncode == 0, res.stdout + res.stderr
        assert f"sidecar: {url}" in res.stdout
        assert httpx.get(url + "healthz", timeout=5.0).status_code == 200
        assert httpx.get(url + "v1/config", timeout=5.0).json()["window_size"] == 7
    finally:
        subprocess.run(down, capture_output=True, env=env, timeout=120)  # whatever is left of either


def test_a_foreground_up_whose_output_is_closed_still_stops_its_stack_at_its_duration():
    """``up ... | head -1``: the first print into the closed pipe had raised out of the watch loop, ``up`` exited
    1 and left every program running past --duration. It now goes on quietly, stops the stack when its duration
    ends, and exits 0."""
    xdg = tempfile.mkdtemp(prefix="jgh")  # short: supervisord's socket path must fit AF_UNIX's 108 bytes
    env = {**os.environ, "XDG_RUNTIME_DIR": xdg}
    name = "headless"
    args = [*_up_args(name, free_tcp_port(), free_tcp_port()), "--duration", "12"]
    try:
        proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
        assert proc.stdout is not None and proc.stdout.readline().startswith("jitterguard: starting")
        proc.stdout.close()  # what `head -1` does after its line
        err = proc.communicate(timeout=120)[1]
        assert proc.returncode == 0, err
        assert "Traceback" not in err, err
        status = subprocess.run([sys.executable, "-m", "jitterguard.cli", "status", "--name", name],
                                capture_output=True, text=True, env=env, timeout=60)
        assert "not running" in status.stdout + status.stderr, status.stdout + status.stderr
    finally:
        subprocess.run([sys.executable, "-m", "jitterguard.cli", "down", "--name", name], capture_output=True,
                       env=env, timeout=120)
        shutil.rmtree(xdg, ignore_errors=True)
