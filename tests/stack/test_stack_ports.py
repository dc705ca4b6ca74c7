"""`up`'s port clash check judges a clash by the address a program binds, not by the port alone.

A port taken on 127.0.0.1 clashes with a bind on 127.0.0.1 and on a wildcard (0.0.0.0, ::), not with a bind on
another specific address (127.0.0.2, ::1): the kernel lets both bind. The check had compared the ports of another
running stack (whose programs may not listen yet) and of this stack's own programs by number alone, so it refused
a sidecar on 127.0.0.2:P beside a router on 127.0.0.1:P. No supervisord here: another stack is a run directory
with its stack.json that `running_run_dirs` names.
"""

from __future__ import annotations

import socket

import pytest

from jitterguard.stack import cli as stack_cli
from jitterguard.stack.status import save_spec
from jitterguard.stack.supervisor import StackSpec
from jitterguard.stack.validate import binds_overlap


@pytest.mark.parametrize(("a", "b", "overlap"), [
    ("127.0.0.1", "127.0.0.1", True),
    ("127.0.0.1", "0.0.0.0", True),
    ("0.0.0.0", "127.0.0.2", True),
    ("127.0.0.1", "127.0.0.2", False),
    ("127.0.0.1", "localhost", True),  # a name is judged by the address it binds
    ("::", "127.0.0.1", True),  # a dual-stack wildcard takes the IPv4 port too
    ("::", "0.0.0.0", True),
    ("::1", "127.0.0.1", False),
    ("::1", "0.0.0.0", False),
    ("::1", "::", True),
    ("::ffff:127.0.0.1", "127.0.0.1", True),
    ("", "127.0.0.1", True),  # no host: every address
])
def test_two_binds_overlap_as_the_kernel_judges_them(a, b, overlap):
    assert binds_overlap(a, b) is overlap
    assert binds_overlap(b, a) is overlap


@pytest.mark.parametrize(("a", "b"), [("127.0.0.1", "127.0.0.2"), ("127.0.0.1", "0.0.0.0"), ("::1", "0.0.0.0")])
def test_the_rule_agrees_with_the_kernel(a, b):
    """What :func:`binds_overlap` says is what a second bind on the same port meets (SO_REUSEADDR, as the router
    and the sidecar bind)."""
    def bound(host: str, port: int = 0) -> socket.socket:
        s = socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET)
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        s.bind((host, port))
        s.listen()
        return s

    first = bound(a)
    try:
        try:
            bound(b, first.getsockname()[1]).close()
            clash = False
        except OSError:
            clash = True
    finally:
        first.close()
    assert clash is binds_overlap(a, b)


@pytest.fixture
def other_stack(tmp_path, monkeypatch):
    """Another stack 'other' that runs (its supervisord's command line names its run dir), router on 127.0.0.1 and
    sidecar on 127.0.0.2, neither listening yet."""
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(tmp_path / "xdg"))
    rd = stack_cli.base_dir() / "other"
    rd.mkdir(parents=True)
    spec = StackSpec(name="other", router_port=7447, sidecar_host="127.0.0.2", sidecar_port=8000, run_dir=str(rd))
    save_spec(rd, spec)
    monkeypatch.setattr(stack_cli, "running_run_dirs", lambda: [rd])
    return stack_cli.base_dir() / "mine"


@pytest.mark.parametrize(("host", "port", "clash"), [
    ("127.0.0.1", 8000, False),  # the other's sidecar is on 127.0.0.2 alone: 127.0.0.1:8000 is free
    ("::1", 8000, False),
    ("127.0.0.2", 8000, True),
    ("0.0.0.0", 8000, True),
    ("::", 8000, True),
    ("127.0.0.1", 7447, True),  # its router's
    ("0.0.0.0", 7447, True),
    ("127.0.0.2", 7447, False),
])
def test_another_stacks_port_clashes_only_where_the_binds_overlap(other_stack, host, port, clash):
    owner = stack_cli._port_owner(host, port, other_stack)
    assert (owner is not None) is clash, owner
    if clash:
        assert owner == ("the stack 'other'", "jitterguard down --name other")


@pytest.mark.parametrize(("wanted", "refused"), [
    ([(7447, "127.0.0.1", "--router-port"), (7447, "127.0.0.2", "--port")], None),
    ([(7447, "127.0.0.1", "--router-port"), (7447, "0.0.0.0", "--port")], "--port 7447 is also the --router-port"),
    ([(7447, "127.0.0.1", "--router-port"), (7447, "localhost", "--port")], "--port 7447 is also the --router-port"),
    ([(7447, "127.0.0.1", "--router-port"), (8765, "127.0.0.1", "--foxglove-port")], None),
])
def test_this_stacks_own_ports_clash_only_where_the_binds_overlap(wanted, refused):
    assert stack_cli._own_clash(wanted) == (refused and f"{refused}; give each its own port")
