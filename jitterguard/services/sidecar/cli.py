"""``jitterguard sidecar`` (the HTTP sidecar under uvicorn).

Bad input is reported on one line with exit status 2 before anything starts (no Zenoh session opened, no
port bound): an unusable port, a non-loopback bind without ``JG_API_TOKEN``, a malformed Zenoh flag.

Commands import their implementation when they run (start-up time: see :mod:`jitterguard.cli`).
"""

from __future__ import annotations

import contextlib
import signal
import socket
import sys
import threading
from collections.abc import Callable, Iterator
from typing import TYPE_CHECKING, Annotated

import typer

from ...cli_common import ConnectOpt, ListenOpt, LogLevelOpt, NsOpt, ZenohConfigOpt, fail, parse_float, parse_int, zenoh_options
from ...schemas import keys

if TYPE_CHECKING:
    from .app import SidecarSettings

HostOpt = Annotated[str, typer.Option("--host", help="Address to bind; non-loopback needs JG_API_TOKEN.")]
PortOpt = Annotated[str, typer.Option("--port", help="TCP port to bind (1-65535).")]
CorsOpt = Annotated[list[str] | None, typer.Option(
    "--cors-origin", help="Allow this browser origin (repeatable). CORS is off unless given.")]
AllowedHostOpt = Annotated[list[str] | None, typer.Option(
    "--allowed-host", help="A host name this sidecar answers to besides its IP address (and localhost on "
                           "loopback), e.g. the vehicle's DNS name (repeatable). Other Host headers get 400.")]
PollOpt = Annotated[str, typer.Option("--poll-ms", help="How often to refresh the classifier state cache, ms.")]


def _parse_port(text: str) -> int:
    return parse_int("--port", text, 1, 65535)


def _check_bindable(host: str, port: int) -> None:
    """Fail now, on one line, if uvicorn could not bind (it would only log it after opening Zenoh)."""
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    except (socket.gaierror, UnicodeError) as exc:
        fail(f"--host: cannot resolve {host!r}: {exc}")
    family, stype, proto, _, addr = infos[0]
    with socket.socket(family, stype, proto) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind(addr)
        except OSError as exc:
            fail(f"--port: cannot bind {host}:{port}: {exc.strerror or exc}")


def register(app: typer.Typer, bench_app: typer.Typer) -> None:
    """Add ``jitterguard sidecar``."""

    @app.command("sidecar")
    def sidecar(
        ns: NsOpt = keys.DEFAULT_NS,
        zenoh_config: ZenohConfigOpt = None,
        connect: ConnectOpt = None,
        listen: ListenOpt = None,
        host: HostOpt = "127.0.0.1",
        port: PortOpt = "8000",
        cors_origin: CorsOpt = None,
        allowed_host: AllowedHostOpt = None,
        poll_ms: PollOpt = "50",
        log_level: LogLevelOpt = "INFO",
    ) -> None:
        """HTTP sidecar: live classifier state, tunable thresholds, metrics and a bird's-eye page."""
        from ...runtime import setup_logging
        from .app import SidecarSettings
        from .core import bind_refusal

        opts = zenoh_options(ns, zenoh_config, connect, listen)
        port_n = _parse_port(port)
        poll_s = parse_float("--poll-ms", poll_ms, 5.0, 10_000.0) / 1e3
        token = SidecarSettings.token_from_env()
        if not host.strip():  # had been refused as a bind to every address without JG_API_TOKEN
            fail("--host: empty; give an address to bind (127.0.0.1: loopback only)")
        reason = bind_refusal(host, token)
        if reason:
            fail(reason)
        for origin in cors_origin or ():
            if not origin.startswith(("http://", "https://")) and origin != "*":
                fail(f"--cors-origin: {origin!r} must look like https://host[:port]")
        for name in allowed_host or ():
            if not name or any(c in name for c in "/:@ \t") or name != name.strip():
                fail(f"--allowed-host: {name!r} must be a bare host name (no scheme, port or path)")
        _check_bindable(host, port_n)
        setup_logging(log_level)
        serve(SidecarSettings(zenoh=opts, api_token=token, cors_origins=tuple(cors_origin or ()),
                              poll_period_s=poll_s, bind_host=host, allowed_hosts=tuple(allowed_host or ())),
              host, port_n, log_level)

GIL_SWITCH_INTERVAL_S = 0.001
REQUEST_READ_TIMEOUT_S = 20.0
"""A request must arrive whole — request line, headers and body — within this long of its first byte (of the
connection, for its first request); else the connection is closed. uvicorn has no such deadline: a connection that
sent nothing, or one header line a minute, or a body a byte at a time, was held for ever, and 20,000 of them (one
process's file limit) left the sidecar unable to accept a connection — ``/healthz`` and ``/readyz`` timed out —
for as long as the client kept them open. A real request takes milliseconds (its body is at most 64 KB)."""


def serve(settings: SidecarSettings, host: str, port: int, log_level: str = "INFO") -> None:
    """Run the sidecar under uvicorn until SIGINT/SIGTERM.

    The GIL switch interval drops from Python's 5 ms to 1 ms in this process: the state poll thread decodes
    and renders every new snapshot (milliseconds of Python at 500 tracks), and with the default interval a
    request arriving meanwhile waits for it in 5 ms slices. Measured with ``jitterguard bench sidecar``:
    about half the p99 of ``GET /v1/state`` at 500 tracks; the process does little else, so the extra
    switching costs nothing that matters.
    """
    import uvicorn

    from .app import create_app

    sys.setswitchinterval(GIL_SWITCH_INTERVAL_S)

    stopping = threading.Event()  # a signal during startup ends the wait for the router (create_app)
    app = create_app(settings, stopping=stopping)
    config = uvicorn.Config(app, host=host, port=port,
                            log_level=log_level.lower(), access_log=log_level.upper() == "DEBUG",
                            timeout_graceful_shutdown=2, lifespan="on", http=_read_deadline_protocol())
    _clean_exit_server_class()(config, stopping, app.state.sidecar.broker.close).run()


def _read_deadline_protocol() -> type:
    """uvicorn's h11 protocol with :data:`REQUEST_READ_TIMEOUT_S` on reading each request (its keep-alive timeout
    only covers the wait between two requests, and the first byte of a request cancels it)."""
    import h11
    from uvicorn.protocols.http.h11_impl import H11Protocol

    class ReadDeadlineH11(H11Protocol):
        _deadline = None

        def connection_made(self, transport) -> None:  # type: ignore[no-untyped-def]
            super().connection_made(transport)
            self._deadline = self.loop.call_later(REQUEST_READ_TIMEOUT_S, self._read_timed_out)

        def data_received(self, data: bytes) -> None:
            super().data_received(data)
            reading = self.conn.their_state in (h11.IDLE, h11.SEND_BODY)  # a request begun and not yet whole
            if reading and self._deadline is None:
                self._deadline = self.loop.call_later(REQUEST_READ_TIMEOUT_S, self._read_timed_out)
            elif not reading:
                self._cancel_deadline()

        def connection_lost(self, exc: Exception | None) -> None:
            self._cancel_deadline()
            super().connection_lost(exc)

        def _cancel_deadline(self) -> None:
            if self._deadline is not None:
                self._deadline.cancel()
                self._deadline = None

        def _read_timed_out(self) -> None:
            self._deadline = None
            if not self.transport.is_closing():
                self.transport.close()

    return ReadDeadlineH11


def _clean_exit_server_class() -> type:
    """Built on demand: uvicorn is imported only by the commands that serve."""
    import uvicorn

    class CleanExitServer(uvicorn.Server):
        """uvicorn's server, exiting 0 after a graceful SIGTERM/SIGINT shutdown.

        Stock uvicorn re-raises the signal once it has shut down, so the process dies "terminated by SIGTERM"
        and supervisord logs every ordinary stop as a warning; the shutdown itself was clean.
        """

        def __init__(self, config: uvicorn.Config, stopping: threading.Event,
                     end_streams: Callable[[], None]) -> None:
            super().__init__(config)
            self.stopping = stopping
            self.end_streams = end_streams

        async def shutdown(self, sockets: list[socket.socket] | None = None) -> None:
            """End the open event streams first, then uvicorn's shutdown: it waits (2 s) for every response to
            finish, and an event stream finishes only when told to. The streams had been told in the lifespan's
            shutdown, which comes after that wait: each was cancelled mid-response instead (its client got a
            body cut short, the log a CancelledError traceback), and every stop took the full 2 s."""
            self.end_streams()
            await super().shutdown(sockets)

        def handle_exit(self, sig: int, frame: object) -> None:
            self.stopping.set()
            super().handle_exit(sig, frame)  # type: ignore[arg-type]

        @contextlib.contextmanager
        def capture_signals(self) -> Iterator[None]:
            if threading.current_thread() is not threading.main_thread():
                yield
                return
            old = {sig: signal.signal(sig, self.handle_exit) for sig in (signal.SIGINT, signal.SIGTERM)}
            try:
                yield
            finally:
                for sig, handler in old.items():
                    signal.signal(sig, handler)

    return CleanExitServer

