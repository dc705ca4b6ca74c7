"""deploy/supervisord.conf, the file an operator runs under their own supervisord, runs as shipped (real
supervisord, real router, services and uvicorn; no mocks).

Only what a test host cannot have is changed: the system folders (/run, /var/log, /var/lib) become temporary ones,
the venv path the one running this test, the ports free ones, ``user=`` / ``chown=`` go (no ``jitterguard`` user
here; the tests at the end keep them, as root, in a mount namespace of their own), and ``JG_WATCHDOG_S`` is short
so that the freeze watch acts within ~15 s. Every program starts, the
sidecar comes ready, the monitor writes the run's summary into /var/lib/jitterguard's stand-in (and the classifier
its compiled statistic's cache, NUMBA_CACHE_DIR), and a service
frozen with SIGSTOP is ended by the monitor and restarted by supervisord. Before, this file had no monitor: a
frozen process stayed frozen for good under plain supervisord, every program RUNNING.

Nothing here asserts a time: every wait is for a condition, with a generous limit (shared 2-core machines).
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
from pathlib import Path

import httpx
import pytest

from jitterguard.runtime import free_tcp_port
from jitterguard.stack.control import StackUnavailable, Supervisor

from helpers import freeze_until_replaced, stop_process, wait_until

pytestmark = pytest.mark.integration

SHIPPED = Path(__file__).resolve().parents[2] / "deploy" / "supervisord.conf"
PROGRAMS = {"monitor", "monitor-watch", "router", "classifier", "tracker", "detector", "sidecar"}
TIMEOUT_S = 120.0


def _localise(text: str, root: Path, router: int, http: int, ns: str, *, as_user: bool = False) -> str:
    """The shipped file with this host's folders, venv, ports and namespace; nothing else changed (``user=`` and
    ``chown=`` dropped unless ``as_user``)."""
    bin_dir = Path(sys.executable).parent
    for system, here in (("/run/jitterguard", root / "run"), ("/var/log/jitterguard", root / "log"),
                         ("/var/lib/jitterguard", root / "lib"), ("/opt/jitterguard/venv/bin", bin_dir)):
        text = text.replace(system, str(here))
    text = text.replace("tcp/127.0.0.1:7447", f"tcp/127.0.0.1:{router}").replace("--port 8000", f"--port {http}")
    text = text.replace('JG_NS="default"', f'JG_NS="{ns}",JG_WATCHDOG_S="3"')
    if as_user:
        return text
    return "\n".join(line for line in text.splitlines() if not line.startswith(("user=", "chown=")))


def _pid(sup: Supervisor, name: str) -> int | None:
    try:
        return next((p.pid for p in sup.processes() if p.name == name and p.state == "RUNNING"), None)
    except StackUnavailable:
        return None


def _wait_all_running(sup: Supervisor) -> None:
    def all_running() -> bool:
        try:
            return {p.name for p in sup.processes() if p.state == "RUNNING"} >= PROGRAMS
        except StackUnavailable:
            return False

    assert wait_until(all_running, timeout=TIMEOUT_S, period=0.5), [(p.name, p.state) for p in sup.processes()]


def _ready(url: str) -> bool:
    try:
        return httpx.get(f"{url}/readyz", timeout=5.0).status_code == 200
    except httpx.HTTPError:
        return False


@pytest.fixture(scope="module")
def deployed(tmp_path_factory):
    root = tmp_path_factory.mktemp("deploy")
    for sub in ("run", "log", "lib"):
        (root / sub).mkdir()
    router, http = free_tcp_port(), free_tcp_port()
    conf = root / "supervisord.conf"
    text = _localise(SHIPPED.read_text(), root, router, http, f"deploy{os.getpid()}")
    settings = "\n".join(line for line in text.splitlines() if not line.startswith(";"))
    assert not re.search(r"(/var/(log|lib)|/run|/opt)/jitterguard", settings), settings
    conf.write_text(text)
    env = {k: v for k, v in os.environ.items() if not k.startswith(("SUPERVISOR_", "JG_"))}
    res = subprocess.run([str(Path(sys.executable).parent / "supervisord"), "-c", str(conf)], env=env,
                         capture_output=True, text=True, timeout=60)
    assert res.returncode == 0, res.stdout + res.stderr
    sup = Supervisor(root, label="deploy", sock=root / "run" / "supervisor.sock")
    info = {"root": root, "sup": sup, "url": f"http://127.0.0.1:{http}"}
    try:
        yield info
    finally:
        try:
            sup.shutdown()
        except StackUnavailable:
            pass
        pidfile = root / "run" / "supervisord.pid"
        wait_until(lambda: not pidfile.exists(), timeout=60, period=0.5)


def test_every_program_of_the_shipped_file_runs_and_the_monitor_keeps_the_summary(deployed):
    sup, root = deployed["sup"], deployed["root"]
    _wait_all_running(sup)
    # the live ROS 2 programs wait for an operator on a vehicle (autostart=false), and then start
    assert {p.name: p.state for p in sup.processes() if p.name.startswith("ros2-")} == {"ros2-in": "STOPPED",
                                                                                        "ros2-out": "STOPPED"}
    for name in ("ros2-in", "ros2-out"):
        sup.call("startProcess", name, True)
    assert {p.name: p.state for p in sup.processes() if p.name.startswith("ros2-")} == {"ros2-in": "RUNNING",
                                                                                        "ros2-out": "RUNNING"}
    assert wait_until(lambda: _ready(deployed["url"]), timeout=TIMEOUT_S, period=1.0), \
        httpx.get(f"{deployed['url']}/readyz", timeout=5.0).text

    def summarised() -> dict | None:
        try:
            body = json.loads((root / "lib" / "summary.json").read_text())
        except (OSError, ValueError):
            return None
        return body if {"classifier", "tracker", "detector"} <= set(body.get("ledger", {})) else None

    assert wait_until(lambda: summarised() is not None, timeout=TIMEOUT_S, period=1.0), \
        (root / "log" / "monitor.log").read_text()[-2000:]
    # the operator's view of it, as the deployment page says: a second reader of the same file
    res = subprocess.run([sys.executable, "-m", "jitterguard.cli", "summary", "--run-dir", str(root / "lib"),
                          "--json"], capture_output=True, text=True, timeout=60)
    assert res.returncode == 0, res.stdout + res.stderr
    assert json.loads(res.stdout)["stack"] == "lib"
    # the classifier caches its compiled statistic where the file's NUMBA_CACHE_DIR says, the one folder its user may
    # write (under user=jitterguard neither the root-owned venv nor root's HOME is writable: each start recompiled)
    cache = root / "lib" / "numba-cache"
    assert wait_until(lambda: any(cache.rglob("*.nbi")), timeout=TIMEOUT_S, period=1.0), \
        (root / "log" / "classifier.log").read_text()[-2000:]
    assert "no writable numba cache" not in (root / "log" / "classifier.log").read_text()


def test_a_frozen_service_is_ended_and_restarted_under_plain_supervisord(deployed):
    """The tracker stopped with SIGSTOP runs no thread, neither its watchdog nor faulthandler's timer; the monitor
    (which found this supervisord by SUPERVISOR_SERVER_URL and knows the tracker for one of its programs by the
    same variable in the tracker's environment) kills it, and supervisord starts it again."""
    sup, root = deployed["sup"], deployed["root"]
    assert wait_until(lambda: _pid(sup, "tracker") is not None and _ready(deployed["url"]),
                      timeout=TIMEOUT_S, period=1.0)
    freeze_until_replaced(lambda: _pid(sup, "tracker"), root / "log" / "monitor.log", TIMEOUT_S)
    assert wait_until(lambda: _ready(deployed["url"]), timeout=TIMEOUT_S, period=1.0)


def test_a_stopped_monitor_is_ended_by_the_shipped_monitor_watch(deployed):
    """The monitor stopped itself (SIGSTOP) had been ended by nothing under this file: the monitor-watch event
    listener sees it stopped in /proc, kills it for supervisord to restart it, and counts it beside the summary."""
    sup, root = deployed["sup"], deployed["root"]
    _wait_all_running(sup)
    monitor = _pid(sup, "monitor")
    assert monitor
    os.kill(monitor, signal.SIGSTOP)
    try:
        assert wait_until(lambda: _pid(sup, "monitor") not in (None, monitor), timeout=TIMEOUT_S, period=0.5), \
            (root / "log" / "monitor-watch.log").read_text()[-2000:]
    finally:
        if _pid(sup, "monitor") == monitor:
            os.kill(monitor, signal.SIGCONT)
    assert f"monitor (pid {monitor}) has been stopped for" in (root / "log" / "monitor-watch.log").read_text()
    assert json.loads((root / "lib" / "monitor-watch.json").read_text())["frozen_restarts"] == {"monitor": 1}


def test_the_monitor_takes_for_a_program_only_what_its_supervisord_started(tmp_path):
    """The monitor SIGKILLs by pid; a pid is taken for a program only if the process's environment names this
    supervisord's socket (supervisord gives every program SUPERVISOR_SERVER_URL): a process of another
    supervisord, one started by hand, and a pid gone are never signalled."""
    sock = tmp_path / "supervisor.sock"
    sup = Supervisor(tmp_path, sock=sock)
    env = {k: v for k, v in os.environ.items() if not k.startswith("SUPERVISOR_")}
    sleep = [sys.executable, "-c", "import time; time.sleep(60)"]
    ours = subprocess.Popen(sleep, env={**env, "SUPERVISOR_SERVER_URL": f"unix://{tmp_path}/./supervisor.sock"})
    other = subprocess.Popen(sleep, env={**env, "SUPERVISOR_SERVER_URL": f"unix://{tmp_path}/other.sock"})
    by_hand = subprocess.Popen(sleep, env=env)
    try:
        assert sup.started(ours.pid)  # the same socket, however the path was spelled
        assert not sup.started(other.pid) and not sup.started(by_hand.pid)
        assert not sup.kill(other.pid) and not sup.kill(by_hand.pid)
        assert other.poll() is None and by_hand.poll() is None
        assert sup.kill(ours.pid)
        assert ours.wait(timeout=30) == -signal.SIGKILL
        assert not sup.started(ours.pid) and not sup.kill(ours.pid)  # reaped: no such pid any more
    finally:
        for proc in (ours, other, by_hand):
            proc.kill()
            proc.wait(timeout=30)


def test_the_monitor_refuses_an_address_that_is_not_a_unix_socket(tmp_path):
    res = subprocess.run([sys.executable, "-m", "jitterguard.cli", "stack-monitor", "--run-dir", str(tmp_path),
                          "--supervisor-url", "http://127.0.0.1:9001"], capture_output=True, text=True, timeout=60)
    assert res.returncode == 2
    assert res.stderr.strip() == ("jitterguard: error: --supervisor-url: 'http://127.0.0.1:9001' is not a unix "
                                  "socket address (unix:///path/to/supervisor.sock)")


# ------------------------------------------------------------------------------------------------------------
# The same file as shipped, user= and chown= included: every program runs as the unprivileged user jitterguard.
#
# A test host has no such user, and its Python may live where no other user can reach (here under root's 0700
# home). Both are arranged inside a private mount namespace that only supervisord and its programs live in, so the
# host is left as it was: /etc/passwd and /etc/group are bind-mounted copies that add the user (unless the host has
# one), and each folder on the way to the interpreter, the venv and the project that other users cannot enter is
# overlaid with an empty upper layer that can be entered (its files keep their own modes). The run's folders lie
# outside every overlay, so what the programs write is what this test reads.

DEPLOY_USER = "jitterguard"


def _unreachable_dirs(paths: list[Path]) -> list[Path]:
    """Folders on the way to ``paths`` that other users may not enter (no execute bit for others)."""
    out: list[Path] = []
    for path in paths:
        for d in reversed([path, *path.parents]):
            if d.is_dir() and not os.stat(d).st_mode & 0o001 and d not in out:
                out.append(d)
    return out


def _user_ids() -> tuple[int, int, bool]:
    """(uid, gid, whether the passwd/group copies must add them): the host's jitterguard user if it has one, else
    the first id from 61000 that no user or group holds."""
    import grp
    import pwd

    try:
        pw = pwd.getpwnam(DEPLOY_USER)
        return pw.pw_uid, pw.pw_gid, False
    except KeyError:
        pass
    used = {p.pw_uid for p in pwd.getpwall()} | {g.gr_gid for g in grp.getgrall()}
    uid = next(i for i in range(61000, 62000) if i not in used)
    return uid, uid, True


@pytest.fixture(scope="module")
def deployed_as_user():
    import shutil
    import tempfile

    if os.geteuid() != 0 or shutil.which("unshare") is None:
        pytest.skip("needs root and unshare(1): supervisord switches to the user jitterguard only when run as root")
    base = Path(tempfile.gettempdir())
    if _unreachable_dirs([base]):
        pytest.skip(f"the temporary folder {base} cannot be entered by other users")
    root = Path(tempfile.mkdtemp(prefix="jg-deploy-user-", dir=base))
    uid, gid, add = _user_ids()
    try:
        root.chmod(0o755)
        for sub in ("run", "log", "lib"):
            (root / sub).mkdir(mode=0o755)
        os.chown(root / "lib", uid, gid)  # as the file's header says: chown jitterguard /var/lib/jitterguard
        passwd, group = (root / "passwd", root / "group")
        passwd.write_text(Path("/etc/passwd").read_text()
                          + (f"{DEPLOY_USER}:x:{uid}:{gid}::/nonexistent:/usr/sbin/nologin\n" if add else ""))
        group.write_text(Path("/etc/group").read_text() + (f"{DEPLOY_USER}:x:{gid}:\n" if add else ""))
        project = Path(__file__).resolve().parents[2]
        needed = [Path(os.path.realpath(sys.executable)), Path(sys.base_prefix), Path(sys.prefix), project]
        mounts = [f"mount --bind {passwd} /etc/passwd", f"mount --bind {group} /etc/group"]
        for i, d in enumerate(_unreachable_dirs([p.resolve() for p in needed])):
            up, work = root / "overlay" / f"{i}-up", root / "overlay" / f"{i}-work"
            up.mkdir(parents=True)
            work.mkdir()
            up.chmod(os.stat(d).st_mode & 0o7777 | 0o011)  # the merged folder's mode is the upper layer's
            mounts.append(f"mount -t overlay overlay -o lowerdir={d},upperdir={up},workdir={work} {d}")
        router, http = free_tcp_port(), free_tcp_port()
        conf = root / "supervisord.conf"
        conf.write_text(_localise(SHIPPED.read_text(), root, router, http, f"deployu{os.getpid()}", as_user=True))
        env = {k: v for k, v in os.environ.items() if not k.startswith(("SUPERVISOR_", "JG_"))}
        script = " && ".join([*mounts, f"exec {Path(sys.executable).parent / 'supervisord'} -c {conf}"])
        res = subprocess.run(["unshare", "--mount", "--propagation", "private", "sh", "-c", script], env=env,
                             capture_output=True, text=True, timeout=60)
        if res.returncode != 0 and "mount" in res.stderr and not (root / "run" / "supervisord.pid").exists():
            pytest.skip(f"no private mounts here: {res.stderr.strip()[:200]}")
        assert res.returncode == 0, res.stdout + res.stderr
        sup = Supervisor(root, label="deploy-user", sock=root / "run" / "supervisor.sock")
        try:
            yield {"root": root, "sup": sup, "url": f"http://127.0.0.1:{http}", "uid": uid, "gid": gid,
                   "router": router, "env": env}
        finally:
            try:
                sup.shutdown()
            except StackUnavailable:
                pass
            wait_until(lambda: not (root / "run" / "supervisord.pid").exists(), timeout=60, period=0.5)
    finally:
        shutil.rmtree(root, ignore_errors=True)


def _uid_of(pid: int) -> int:
    status = Path(f"/proc/{pid}/status").read_text()
    return int(re.search(r"^Uid:\s+(\d+)", status, re.M).group(1))


def test_the_shipped_file_runs_every_program_as_its_unprivileged_user(deployed_as_user):
    """user=jitterguard and chown=root:jitterguard as shipped: every program runs under the user's uid, never
    root's; the monitor, as that user, reaches supervisord through the socket the file hands to the user's group,
    keeps the summary and the classifier its compiled statistic's cache in the one folder the user owns, and ends a
    frozen service for supervisord to restart."""
    d = deployed_as_user
    sup, root, uid = d["sup"], d["root"], d["uid"]
    _wait_all_running(sup)
    pids = {p.name: p.pid for p in sup.processes() if p.name in PROGRAMS}
    assert {name: _uid_of(pid) for name, pid in pids.items()} == {name: uid for name in pids}
    sock = os.stat(root / "run" / "supervisor.sock")
    assert (sock.st_uid, sock.st_gid, sock.st_mode & 0o777) == (0, d["gid"], 0o770)
    assert wait_until(lambda: _ready(d["url"]), timeout=TIMEOUT_S, period=1.0), \
        (root / "log" / "sidecar.log").read_text()[-2000:]

    summary = root / "lib" / "summary.json"

    def summarised() -> bool:
        try:
            body = json.loads(summary.read_text())
        except (OSError, ValueError):
            return False
        return {"classifier", "tracker", "detector"} <= set(body.get("ledger", {}))

    assert wait_until(summarised, timeout=TIMEOUT_S, period=1.0), (root / "log" / "monitor.log").read_text()[-2000:]
    assert os.stat(summary).st_uid == uid
    cache = root / "lib" / "numba-cache"
    assert wait_until(lambda: any(cache.rglob("*.nbi")), timeout=TIMEOUT_S, period=1.0), \
        (root / "log" / "classifier.log").read_text()[-2000:]
    assert all(p.stat().st_uid == uid for p in cache.rglob("*.nbi"))

    freeze_until_replaced(lambda: _pid(sup, "tracker"), root / "log" / "monitor.log", TIMEOUT_S)
    assert _uid_of(_pid(sup, "tracker")) == uid


def test_a_monitor_whose_user_the_socket_refuses_says_so(deployed_as_user):
    """The same user without the socket's group (a deployment whose chown= leaves the monitor's user out): the
    client names the refusal instead of taking supervisord for one still starting, and a monitor run so logs it
    once and reports itself failing in its heartbeat. Before, its watch skipped every look in silence — "monitor
    up" the last line of its log — and a frozen service stayed frozen."""
    from jitterguard.stack.status import probe_zenoh

    d = deployed_as_user
    root, uid = d["root"], d["uid"]
    sock = root / "run" / "supervisor.sock"
    pid = int((root / "run" / "supervisord.pid").read_text())
    # in supervisord's mount namespace (where the interpreter can be reached), as the user but not in its group
    as_user = ["nsenter", "--target", str(pid), "--mount", "setpriv", f"--reuid={uid}", "--regid=65534",
               "--clear-groups", sys.executable]
    probe = ("import json\nfrom pathlib import Path\nfrom jitterguard.stack.control import Supervisor, "
             "StackUnavailable\ntry:\n    Supervisor(Path('/nonexistent'), sock=Path(%r)).processes()\n"
             "except StackUnavailable as exc:\n    print(json.dumps([exc.state, str(exc)]))\n") % str(sock)
    res = subprocess.run([*as_user, "-c", probe], env=d["env"], capture_output=True, text=True, timeout=60)
    assert res.returncode == 0, res.stderr
    state, message = json.loads(res.stdout)
    assert state == "denied", message
    assert f"(uid {uid}) may not use supervisord's socket {sock}" in message
    # `down` by that user: an error that says why, not "is starting or stopping" and exit 0
    res = subprocess.run([*as_user, "-m", "jitterguard.cli", "down", "--run-dir", str(root / "run")], env=d["env"],
                         capture_output=True, text=True, timeout=60)
    assert res.returncode == 1 and "may not use supervisord's socket" in res.stderr, res.stdout + res.stderr
    assert d["sup"].running()

    ns = f"denied{os.getpid()}"  # a namespace of its own: the stack's sidecar and summary never hear it
    mon_dir = root / "lib" / "second-monitor"
    mon_dir.mkdir()
    os.chown(mon_dir, uid, 65534)
    log_path = root / "log" / "second-monitor.log"
    with log_path.open("wb") as log:
        mon = subprocess.Popen([*as_user, "-m", "jitterguard.cli", "stack-monitor", "--run-dir", str(mon_dir),
                                "--supervisor-url", f"unix://{sock}", "--supervisord-log",
                                str(root / "log" / "supervisord.log"), "--ns", ns,
                                "--connect", f"tcp/127.0.0.1:{d['router']}"],
                               env={**d["env"], "JG_WATCHDOG_S": "3", "HOME": str(mon_dir)}, stdout=log,
                               stderr=subprocess.STDOUT)
    try:
        def failing() -> str | None:
            beat = probe_zenoh(ns, f"tcp/127.0.0.1:{d['router']}", 1.5)[1].get("monitor")
            return beat.health_reason if beat is not None and beat.health == "failing" else None

        assert wait_until(lambda: failing() is not None, timeout=TIMEOUT_S, period=0.5), log_path.read_text()
        assert "may not use supervisord's socket" in failing()
        assert wait_until(lambda: "frozen programs and crash loops go unhandled" in log_path.read_text(),
                          timeout=TIMEOUT_S, period=0.5)
    finally:
        stop_process(mon)
    assert log_path.read_text().count("cannot ask supervisord") == 1, log_path.read_text()[-2000:]  # once
