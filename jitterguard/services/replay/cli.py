"""``jitterguard replay SOURCE``.

Bad input (unknown source, bad ``--rate``, missing file) is one line on stderr and exit 2. A frame that
cannot be read is one line naming the file; with ``--on-error skip`` (default) replay goes on and the final
summary counts it, with ``--on-error stop`` replay ends there with exit 65 (:data:`~jitterguard.runtime.service.EXIT_BAD_INPUT`: bad
input, which a supervisor does not restart). A recording none of whose frames reads
replays nothing: one line and exit 2.

Commands import their implementation when they run (start-up time: see :mod:`jitterguard.cli`).
"""

from __future__ import annotations

import logging
import os
import sys
import time
from pathlib import Path
from typing import Annotated, Any

import typer

from ...cli_common import (ConnectOpt, ListenOpt, LogLevelOpt, NsOpt, ProgressOpt, ZenohConfigOpt, check_seed, fail,
                           progress_on, zenoh_options)
from ...runtime import setup_logging
from ...runtime.service import EXIT_BAD_INPUT
from ...runtime.signals import stop_on_signals
from .frames import Frame, FrameError, SourceError
from .options import ReplayOptions
from .runner import ReplayPlan

log = logging.getLogger("jitterguard.replay")
_LOADED_AT = time.monotonic()  # about when this process started (its interpreter, the CLI's imports before this)
SUPERVISED_STOP_AFTER_S = 3.0
"""Under supervisord (``SUPERVISOR_ENABLED``), a stop on bad input exits no sooner than this after the process
started. supervisord takes any exit before a program's ``startsecs`` for a failed start and starts it again (then
gives up: FATAL), whatever its status: a replay that met its bad frame within a second would be restarted, its
deliberate stop read as a crash. The stack's replay has ``startsecs=2``; a hand-written program needs less than
this."""

EXAMPLES = """
Examples:\n
  jitterguard replay synthetic:parking-street --seed 3 --rate 2\n
  jitterguard replay synthetic:mixed --level detections --loop --stamps wall\n
  jitterguard replay ../shared/data/nuscenes-scene-0523 --rate max\n
  jitterguard replay sequences/00/velodyne --poses poses/00.txt --start 100 --limit 50\n
  jitterguard replay run.mcap --topic /sensing/lidar/top/pointcloud --pose-topic /localization/kinematic_state
"""

CONSUMERS = ("detector", "tracker")
"""What ``--wait-for`` may name: the services that consume what a replay publishes (scans, detections). Any name
that fits a key chunk had been taken, so a typo (``detecter``) waited the whole ``--wait-subscriber`` for nobody."""


# The options that say what to replay, shared with `jitterguard up` (which passes them to its replay program).
SourceArg = Annotated[str, typer.Argument(help="synthetic:SCENARIO, a nuScenes dataroot, a bag (.mcap/.db3/folder), a folder of .bin or .pcd scans, or one such file.")]
RateOpt = Annotated[str, typer.Option("--rate", help="Factor on the recorded rate (1 = real time, 2 or 2x = twice as fast; at least 0.001), or 'max'.")]
StartOpt = Annotated[int, typer.Option("--start", help="First recorded frame to replay (0-based).")]
LimitOpt = Annotated[int | None, typer.Option("--limit", help="Replay at most this many frames (per pass when looping).")]
OnErrorOpt = Annotated[str, typer.Option("--on-error", help="A frame that cannot be read: 'skip' (count it, go on) or 'stop' (exit 65, which supervisord and systemd do not restart).")]
SeedOpt = Annotated[int, typer.Option("--seed", help="Synthetic sources and --level detections: scenario and noise seed.")]
LidarOpt = Annotated[str, typer.Option("--lidar", help="Synthetic scans: sensor model (hdl32e, vlp16, os1-64).")]
SceneOpt = Annotated[str | None, typer.Option("--scene", help="nuScenes: scene name or token (needed when the dataroot holds several).")]
NuScenesVersionOpt = Annotated[str | None, typer.Option("--nuscenes-version", help="nuScenes: table folder, e.g. v1.0-mini (default: the only one).")]
SweepsOpt = Annotated[bool, typer.Option("--sweeps", help="nuScenes: replay every LiDAR sweep, not only key frames.")]
PosesOpt = Annotated[str | None, typer.Option("--poses", help="KITTI: odometry poses file (poses/NN.txt).")]
CalibOpt = Annotated[str | None, typer.Option("--calib", help="KITTI: calib.txt with the Tr line (default: calib.txt next to the scans).")]
TimesOpt = Annotated[str | None, typer.Option("--times", help="KITTI: times.txt (default: next to the scans; else --hz).")]
BinFieldsOpt = Annotated[str | None, typer.Option("--bin-fields", help="Raw .bin columns, e.g. x,y,z,intensity (default by name: .pcd.bin has 5, .bin 4).")]
HzOpt = Annotated[float, typer.Option("--hz", help="Frame rate of synthetic sources, and stamp spacing of recordings without time (KITTI without times.txt, .pcd).")]
TopicOpt = Annotated[str | None, typer.Option("--topic", help="Bags: the PointCloud2 or Autoware DetectedObjects topic.")]
PoseTopicOpt = Annotated[str | None, typer.Option("--pose-topic", help="Bags: /tf (TF tree + /tf_static) or an Odometry/PoseStamped topic giving the ego pose.")]


class _Progress:
    """tqdm on stderr when it is a terminal (or forced); error lines go through it so the bar stays intact."""

    def __init__(self, enabled: bool, total: int | None, desc: str, *, stops: bool = False) -> None:
        """``stops``: ``--on-error stop`` — an unreadable frame ends the replay, and its line says so."""
        self.bar: Any = None
        self.verb = "stops the replay" if stops else "skipped"
        if enabled:
            from tqdm import tqdm

            self.bar = tqdm(total=total, desc=desc, unit="scan", file=sys.stderr, leave=True)
        self.errors = 0

    def published(self, _frame: Frame, _seq: int) -> None:
        if self.bar is not None:
            self.bar.update(1)

    def error(self, err: FrameError) -> None:
        self.errors += 1
        line = f"jitterguard: unreadable frame {self.verb}: {err}"
        if self.bar is not None:
            self.bar.set_postfix(errors=self.errors, refresh=False)
            self.bar.write(line, file=sys.stderr)
        else:
            print(line, file=sys.stderr)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


MAX_WAIT_S = 86400.0
"""The longest ``--wait-subscriber``: a day (a replay that must wait longer is started later)."""


def replay_command(
    source: SourceArg,
    rate: RateOpt = "1",
    loop: Annotated[bool, typer.Option("--loop", help="Start over at the end, forever. With --stamps recorded, seq and stamps keep increasing across passes; with --stamps wall too (stamps on the wall clock, going on): every frame follows the last, and the jump back to the recording's start is absorbed by the tracker's gates.")] = False,
    start: StartOpt = 0,
    limit: LimitOpt = None,
    on_error: OnErrorOpt = "skip",
    stamps: Annotated[str, typer.Option("--stamps", help="'recorded': the recording's own stamps (moved forward across --loop passes); 'wall': the first frame gets the current wall-clock time and the rest their recorded spacing after it, like a live sensor (a restarted replay then goes on forward in time instead of rewinding).")] = "recorded",
    level: Annotated[str, typer.Option("--level", help="Sources with ground-truth boxes (synthetic, nuScenes): 'points' (scans) or 'detections' (the boxes through the detection-level noise model).")] = "points",
    seed: SeedOpt = 0,
    duration: Annotated[float, typer.Option("--duration", help="Synthetic sources: scenario length in seconds.")] = 20.0,
    lidar: LidarOpt = "hdl32e",
    scene: SceneOpt = None,
    nuscenes_version: NuScenesVersionOpt = None,
    sweeps: SweepsOpt = False,
    poses: PosesOpt = None,
    calib: CalibOpt = None,
    times: TimesOpt = None,
    bin_fields: BinFieldsOpt = None,
    hz: HzOpt = 10.0,
    topic: TopicOpt = None,
    pose_topic: PoseTopicOpt = None,
    wait_subscriber: Annotated[float, typer.Option("--wait-subscriber", help="Seconds to wait for a subscriber before the first frame (0: do not wait; at most 86400).")] = 5.0,
    wait_for: Annotated[str | None, typer.Option("--wait-for", help="Before the first frame, wait (up to --wait-subscriber seconds) for this service's heartbeat saying it is ready — the pipeline's consumer: detector for scans, tracker for detections — not only for any subscriber (a viewer or recorder subscribed first had started the replay before the detector was up).")] = None,
    progress: ProgressOpt = None,
    ns: NsOpt = "default",
    zenoh_config: ZenohConfigOpt = None,
    connect: ConnectOpt = None,
    listen: ListenOpt = None,
    log_level: LogLevelOpt = "INFO",
) -> None:
    """Replay a recording onto jg/{ns}/points (scans with ego pose) or jg/{ns}/detections."""
    check_seed("--seed", seed)
    setup_logging(log_level)
    opts = ReplayOptions(rate=rate, start=start, limit=limit, on_error=on_error, level=level, seed=seed,
                         duration=duration, lidar=lidar, hz=hz, scene=scene, nuscenes_version=nuscenes_version,
                         sweeps=sweeps, poses=poses, calib=calib, times=times, bin_fields=bin_fields, topic=topic,
                         pose_topic=pose_topic)
    if not 0 <= wait_subscriber <= MAX_WAIT_S:  # nan (every comparison with it is false) and inf had waited for ever
        fail(f"--wait-subscriber must be a number of seconds from 0 to {MAX_WAIT_S:g}, got {wait_subscriber}")
    if wait_for is not None and wait_for not in CONSUMERS:
        fail(f"--wait-for must be {' or '.join(CONSUMERS)} (the consumer of scans, of detections), got {wait_for!r}")
    try:
        src_opts = opts.check()
        plan = opts.plan(loop=loop, stamps=stamps)
    except ValueError as exc:
        fail(str(exc))
    from .sources import open_source
    from .sources.base import check_start

    zopts = zenoh_options(ns, zenoh_config, connect, listen)
    try:
        src = open_source(source, src_opts)
    except SourceError as exc:
        fail(str(exc))
    except Exception as exc:  # a reader that failed in a way it did not foresee: still one line
        fail(f"{source}: cannot open: {type(exc).__name__}: {exc}")
    with src:
        try:  # before the Zenoh session: it had been refused only after the router came up (retried for ever
            # without one) and the wait for a subscriber
            check_start(plan.start, src.info)
        except SourceError as exc:
            fail(str(exc))
        for note in src.info.notes:
            log.info("%s", note)
        for warning in src.info.warnings:
            log.warning("%s", warning)
        from .service import ReplayService

        try:
            svc = ReplayService(zopts, src.info.kind)
        except Exception as exc:
            fail(f"cannot open a Zenoh session: {exc}")
        code = _run(svc, src, plan, wait_subscriber, progress, wait_for)
    if code == EXIT_BAD_INPUT and os.environ.get("SUPERVISOR_ENABLED"):
        _outlive_startsecs()
    raise typer.Exit(code)


def _outlive_startsecs() -> None:
    """Wait until the process has run :data:`SUPERVISED_STOP_AFTER_S`, or until it is told to stop (SIGTERM)."""
    import threading

    left = SUPERVISED_STOP_AFTER_S - (time.monotonic() - _LOADED_AT)
    if left > 0:
        stopped = threading.Event()
        stop_on_signals(stopped.set)
        stopped.wait(left)


def short_name(source_name: str) -> str:
    """The progress bar's label for a source's name: its last path part, without the " (scene…, seed…)" the
    readers add (a folder name may hold spaces: "runs/day 2/velodyne" is "velodyne", not "runs/day")."""
    return Path(source_name.split(" (")[0].rstrip(":")).name or source_name


def _run(svc: Any, src: Any, plan: ReplayPlan, wait_s: float, progress: bool | None,
         wait_for: str | None = None) -> int:
    stop_on_signals(svc.stop)
    try:
        # a wait that a stop (Ctrl-C, supervisord's SIGTERM) ended is no timeout: it had said "not ready after
        # 120.0 s; replaying anyway" of a replay stopped after 3 s that replayed nothing
        if (wait_for is not None and wait_s > 0 and not svc.wait_for_service(wait_for, wait_s)
                and not svc.stop_event.is_set()):
            log.warning("%s not ready after %.1f s; replaying anyway", wait_for, wait_s)
        if wait_s > 0 and not svc.wait_for_subscribers(wait_s) and not svc.stop_event.is_set():
            log.info("no subscriber on %s after %.1f s; replaying anyway", svc.key, wait_s)
        rate_txt = "max" if plan.rate is None else f"x{plan.rate:g}"
        log.info("replaying %s on %s at rate %s%s", src.info.name, svc.key, rate_txt, " (looping)" if plan.loop else "")
        total = None
        if src.info.num_frames is not None and not plan.loop:
            total = max(0, src.info.num_frames - plan.start)
            if plan.limit is not None:
                total = min(total, plan.limit)
        short = short_name(src.info.name)
        bar = _Progress(progress_on(progress), total, short, stops=plan.on_error == "stop")
        try:
            stats = svc.replay(src, plan, on_error=bar.error, on_published=bar.published)
        except SourceError as exc:
            print(f"jitterguard: error: {exc}", file=sys.stderr)
            return 2
        except Exception as exc:  # a failed put (session gone) ends the replay with one line, not a traceback
            log.debug("replay failed", exc_info=True)
            print(f"jitterguard: error: replay failed: {type(exc).__name__}: {exc}", file=sys.stderr)
            return 1
        finally:
            bar.close()
    finally:
        svc.close()
    summary = (
        f"replayed {stats.published} frame(s) on {svc.key} in {stats.passes} pass(es)"
        f"; {stats.errors} unreadable" + (f"; {stats.late} late re-anchor(s)" if stats.late else "")
        + (f"; {stats.reordered} stamp(s) not after the previous one, published 1 ns after it" if stats.reordered
           else "")
        + (f"; the recording's clock stepped back {stats.stepped_back} time(s), its timeline went on"
           if stats.stepped_back else "")
        + (" (interrupted)" if stats.interrupted else "")
    )
    print(f"jitterguard: {summary}", file=sys.stderr)
    if stats.stopped_by is not None:
        print(f"jitterguard: error: stopped at unreadable frame {stats.stopped_by} (--on-error stop; exit status"
              f" {EXIT_BAD_INPUT}, not restarted)", file=sys.stderr)
        return EXIT_BAD_INPUT
    if stats.published == 0 and stats.errors and not stats.interrupted:
        # every frame unreadable: nothing was replayed, which is no success (`jitterguard up` refuses such a
        # recording before it starts, with the same exit status)
        print(f"jitterguard: error: no frame of {src.info.name} could be read ({stats.errors} unreadable)",
              file=sys.stderr)
        return 2
    return 0


def register(app: typer.Typer, bench_app: typer.Typer) -> None:
    """Add ``replay`` to the main app (its benchmark is ``jitterguard bench replay``, :mod:`jitterguard.bench`)."""
    app.command("replay", help=(replay_command.__doc__ or "") + "\n\n" + EXAMPLES)(replay_command)
