"""``jitterguard foxglove``: serve the pipeline live to Foxglove (loopback WebSocket) and/or record it to MCAP."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from ...cli_common import (ConnectOpt, ListenOpt, LogLevelOpt, NsOpt, ZenohConfigOpt, fail, float_option, is_png, out_file,
                          refuse_foreign_file, zenoh_options)

EXAMPLES = """
Examples:\n
  jitterguard foxglove --port 8765                      # then open ws://127.0.0.1:8765 in Foxglove\n
  jitterguard foxglove --record run.mcap --no-server    # record only\n
  jitterguard up --foxglove --record-mcap run.mcap      # the whole stack, viewed and recorded
"""


def register(app: typer.Typer, bench_app: typer.Typer) -> None:
    @app.command("foxglove", help=(
        "Serve the pipeline live over the Foxglove WebSocket protocol (loopback) and/or record it to MCAP: points,"
        " detections with 1σ/2σ ellipses, tracks by motion state with velocity arrows and z labels, ground truth,"
        " frames, and the classifier's per-track statistics.\n\n" + EXAMPLES))
    def foxglove_cmd(
        ns: NsOpt = "default",
        zenoh_config: ZenohConfigOpt = None,
        connect: ConnectOpt = None,
        listen: ListenOpt = None,
        host: Annotated[str, typer.Option("--host", help="Loopback address to bind (the protocol has no authentication; tunnel with ssh -L to view remotely).")] = "127.0.0.1",
        port: Annotated[int, typer.Option("--port", min=0, max=65535, help="WebSocket port (0: any free port).")] = 8765,
        server: Annotated[bool, typer.Option("--server/--no-server", help="Serve live (off: record only).")] = True,
        record: Annotated[str | None, typer.Option("--record", help="Also write every message to this MCAP file.")] = None,
        overwrite: Annotated[bool, typer.Option("--overwrite", help="Replace an existing --record file.")] = False,
        number_if_exists: Annotated[bool, typer.Option("--number-if-exists", help="If the --record file exists, write NAME.1.mcap, NAME.2.mcap, ... instead (for supervised restarts).")] = False,
        points: Annotated[bool, typer.Option("--points/--no-points", help="Subscribe to and forward the scans (the heaviest channel).")] = True,
        motion_wait: Annotated[float, float_option("--motion-wait", min=0.0, max=5.0, help="Seconds a frame waits for its motion/{id} messages after objects.")] = 0.25,
        log_level: LogLevelOpt = "INFO",
    ) -> None:
        from ..sidecar.core import is_loopback

        if not server and record is None:
            fail("--no-server without --record: nothing to do")
        if record is None and (overwrite or number_if_exists):  # had been ignored without a word
            fail(f"{'--overwrite' if overwrite else '--number-if-exists'}: only with --record")
        if overwrite and number_if_exists:  # --overwrite had won without a word
            fail("--overwrite replaces the --record file, --number-if-exists keeps it: give one of them")
        if server and not is_loopback(host):
            fail(f"--host: {host!r} is not a loopback address; the Foxglove protocol has no authentication"
                 " (view remotely through an SSH tunnel)")
        if record is not None:
            if not record.strip():  # Path("") is the current folder: "--record:  is a folder"
                fail("--record: empty path; give a file")
            rp = Path(record)
            if rp.is_dir():
                fail(f"--record: {record} is a folder")
            if rp.exists() and number_if_exists and not overwrite:
                from ..bridge.paths import next_free_path

                rp = next_free_path(rp)
                record = str(rp)
            if rp.exists() and not overwrite:
                fail(f"--record: {record} exists (add --overwrite to replace it)")
            if not rp.parent.is_dir():  # a recorder under a supervisor makes no folders of its own
                fail(f"--record: no folder {rp.parent}")
            out_file("--record", rp)  # tried by opening it: /proc passes a folder test for root
        opts = zenoh_options(ns, zenoh_config, connect, listen)

        from ...runtime import setup_logging

        try:
            from .service import FoxgloveService, FoxgloveSink, SinkStartError
        except ModuleNotFoundError as exc:
            fail(f"jitterguard foxglove needs the foxglove-sdk package (pip install 'jitterguard[foxglove]'): {exc}")

        setup_logging(log_level)
        try:
            sink = FoxgloveSink(host=host, port=port if server else None, mcap_path=record, overwrite=overwrite)
        except SinkStartError as exc:  # the SDK's own errors (port in use, file exists), named by their flag
            fail(f"{'--port' if exc.part == 'server' else '--record'}: {exc}")
        try:
            service = FoxgloveService(opts, sink, points=points, motion_wait_s=motion_wait)
        except ValueError as exc:
            sink.close()
            fail(str(exc))
        if sink.port is not None:
            service.log.info("Foxglove WebSocket server on ws://%s:%d (open it in Foxglove: Open connection)", host,
                             sink.port)
        if record is not None:
            service.log.info("recording to %s", record)
        service.run_forever()

    @app.command("render-mcap")
    def render_mcap_cmd(
        mcap: Annotated[str, typer.Argument(help="A recording of `jitterguard foxglove --record`.")],
        out: Annotated[str, typer.Option("--out", help="PNG to write.")],
        index: Annotated[int | None, typer.Option("--index", help="Frame to draw (negative: from the end). Default: the one with the most static and dynamic tracks.")] = None,
        span: Annotated[float, float_option("--span", min=5.0, max=500.0, help="Half-width of the view around the ego, m.")] = 50.0,
    ) -> None:
        """Draw one recorded frame bird's-eye (scan, ground truth, detection ellipses, tracks by motion state with
        velocity arrows) to a PNG."""
        if Path(mcap).is_dir():
            fail(f"{mcap}: a folder, not an MCAP file")
        if not Path(mcap).is_file():
            fail(f"{mcap}: no such file")
        if not out.lower().endswith(".png"):  # matplotlib would pick the format by the suffix, or add one
            fail("--out must name a .png file")
        refuse_foreign_file("--out", out, is_png, "a PNG")
        out_file("--out", out)
        from .render import RenderError, pick_frame, read_frames, render

        try:
            frame = pick_frame(read_frames(mcap), index)
        except RenderError as exc:
            fail(str(exc))
        try:
            print(render(frame, out, span_m=span))
        except OSError as exc:  # a full disk: one line, and the earlier PNG there is left whole
            fail(f"--out: cannot write {out}: {exc.strerror or exc}")

