"""``jitterguard sim ...`` (generate, export, bev, list).

Bad input is one line on stderr and exit 2 (``cli_common.fail``); long work shows a tqdm bar on stderr.

Commands import their implementation when they run (start-up time: see :mod:`jitterguard.cli`).
"""

from __future__ import annotations

import contextlib
import json
import os
import sys
from collections import Counter
from pathlib import Path
from typing import Annotated, Any, TextIO

import typer

from ..cli_common import ProgressOpt, check_seed, fail, is_png, out_file, progress_on, refuse_foreign_file
from ..runtime.signals import sigterm_as_exit

sim_app = typer.Typer(help="Synthetic world: scenarios with ground truth, ray-cast LiDAR, nuScenes export.",
                      no_args_is_help=True)

ScenarioArg = Annotated[str, typer.Argument(
    help="parking-street, diagonal-lot, intersection, mixed, loading-street, perpendicular-lot or screened-lot.")]
SeedOpt = Annotated[int, typer.Option("--seed", help="Seed: the same seed gives the same world.")]
DurationOpt = Annotated[float, typer.Option("--duration", help="Seconds (10–60 is the intended range).")]
LidarOpt = Annotated[str, typer.Option("--lidar", help="hdl32e, vlp16 or os1-64.")]


def check_scenario_options(scenario: str, duration: float, rate: float, lidar: str | None = None, seed: int = 0,
                           flag: str = "SCENARIO") -> None:
    """Refuse (one line, exit 2) a scenario, duration, rate, LiDAR or seed the world cannot make; ``flag``: what the
    scenario came as (the argument, or ``--scenario`` of the benches, which it had not named)."""
    from .sensors import SENSORS
    from .world import SCENARIO_NAMES

    check_seed("--seed", seed)
    if scenario not in SCENARIO_NAMES:
        fail(f"{flag}: unknown scenario {scenario!r} (have: {', '.join(SCENARIO_NAMES)})")
    if not 0 < duration <= 600:
        fail("--duration must be in (0, 600] seconds")
    if not 0 < rate <= 100:
        fail("--rate must be in (0, 100] Hz")
    from .world import frame_count

    # counted as the world counts (whole frames): a shorter scenario made an empty file or a scene the replay refuses
    if frame_count(duration, rate) < 1:
        fail(f"--duration {duration:g} s at --rate {rate:g} Hz holds no whole frame; make duration × rate at least 1")
    if lidar is not None and lidar not in SENSORS:
        fail(f"--lidar {lidar!r}: unknown sensor (have: {', '.join(SENSORS)})")


def _bar(iterable: Any, total: int, desc: str, enabled: bool) -> Any:
    if not enabled:
        return iterable
    from tqdm import tqdm

    return tqdm(iterable, total=total, desc=desc, unit="frame", file=sys.stderr, leave=False)


def _open_out(out: str) -> tuple[TextIO, str | None]:
    """``--out`` opened for writing, or one line and exit 2; with the temporary file's path when there is one.

    Why a temporary file: ground truth is written frame by frame while the scenario is generated, and a write
    that fails halfway (a full disk) must not leave a truncated file where a complete one is expected — so a
    regular file (or a new one) is written beside itself as ``.NAME.PID.part`` and renamed over ``out`` only
    once complete. Anything else (``/dev/stdout``, a pipe, a symlink) is written in place; so is a file whose
    folder takes no new file."""
    target = Path(out)
    if not target.is_symlink() and (not target.exists() or target.is_file()):
        part = str(target.with_name(f".{target.name}.{os.getpid()}.part"))
        try:
            return open(part, "x", encoding="utf-8"), part
        except OSError:
            pass  # the folder takes no new file (or does not exist): opening out itself says which
    try:
        return open(out, "w", encoding="utf-8"), None
    except OSError as exc:
        fail(f"--out: cannot write {out}: {exc.strerror or exc}")


def _frame_json(frame: Any, categories: dict[int, str]) -> dict[str, Any]:
    return {
        "seq": frame.seq, "stamp_ns": frame.stamp_ns,
        "ego": {"x": frame.ego_x, "y": frame.ego_y, "yaw": frame.ego_yaw, "speed": frame.ego_speed},
        "objects": [
            {"instance_id": int(frame.instance_ids[n]), "label": int(frame.labels[n]),
             "category": categories[int(frame.instance_ids[n])], "attribute": frame.attributes[n],
             "moving": bool(frame.moving[n]), "center": [float(v) for v in frame.centers[n]],
             "size": [float(v) for v in frame.sizes[n]], "yaw": float(frame.yaws[n]),
             "velocity": [float(v) for v in frame.velocities[n]], "visibility": round(float(frame.visibility[n]), 4),
             "num_points": int(frame.num_points[n])}
            for n in range(frame.num_objects)
        ],
    }


def generate_command(
    scenario: ScenarioArg,
    seed: SeedOpt = 0,
    duration: DurationOpt = 20.0,
    rate: Annotated[float, typer.Option("--rate", help="Frames per second.")] = 10.0,
    out: Annotated[str | None, typer.Option("--out", help="Write the ground truth as JSON lines (one frame each).")] = None,
    lidar: Annotated[str | None, typer.Option("--lidar", help="Also ray-cast every frame (hdl32e, vlp16, os1-64) to fill point counts and visibility.")] = None,
    progress: ProgressOpt = None,
) -> None:
    """Generate a scenario; print a JSON summary, optionally write its ground truth."""
    check_scenario_options(scenario, duration, rate, lidar, seed)
    if out is not None and not out.strip():  # had been taken as no --out: nothing written, exit 0
        fail("--out: empty path; give a file")
    from .lidar import cast_frame
    from .sensors import SENSORS
    from .world import make_scenario

    sc = make_scenario(scenario, seed, duration_s=duration, rate_hz=rate)
    spec = SENSORS[lidar]() if lidar else None
    attrs: Counter[str] = Counter()
    ids: set[int] = set()
    if out:  # its own JSON lines are replaced; a user's notes are not
        refuse_foreign_file("--out", out, lambda head: head.startswith(b'{"seq": '), "ground truth written by"
                            " `sim generate`")
    fh, part = _open_out(out) if out else (None, None)
    with sigterm_as_exit():  # a SIGTERM removes the part file as Ctrl-C does
        try:
            frames = _bar(iter(sc), sc.num_frames, scenario, progress_on(progress))
            first = last = None
            for frame in frames:
                if spec is not None:
                    _, frame = cast_frame(frame, spec, seed)
                attrs.update(frame.attributes)
                ids.update(frame.instance_ids.tolist())
                first = first or frame
                last = frame
                if fh is not None:
                    line = json.dumps(_frame_json(frame, sc.categories)) + "\n"
                    try:
                        fh.write(line)
                    except OSError as exc:
                        fail(f"--out: cannot write {out}: {exc.strerror or exc}")
            if fh is not None:
                try:
                    fh.close()  # a full disk may only show here, when the buffer is flushed
                    if part is not None:
                        os.replace(part, out)
                except OSError as exc:
                    fail(f"--out: cannot write {out}: {exc.strerror or exc}")
                part = None
        finally:
            if fh is not None and not fh.closed:
                with contextlib.suppress(OSError):  # already failing: the first error is the one reported
                    fh.close()
            if part is not None:
                with contextlib.suppress(OSError):
                    os.unlink(part)
    summary = {
        "scenario": scenario, "seed": seed, "frames": sc.num_frames, "rate_hz": rate,
        "instances_seen": len(ids), "annotations": sum(attrs.values()), "attributes": dict(sorted(attrs.items())),
        "ego_distance_m": round(float(((last.ego_x - first.ego_x) ** 2 + (last.ego_y - first.ego_y) ** 2) ** 0.5), 2)
        if first is not None and last is not None else 0.0,
    }
    if out:
        summary["out"] = out
    print(json.dumps(summary))


def export_command(
    scenario: ScenarioArg,
    dataroot: Annotated[str, typer.Argument(help="Folder to write (v1.0-mini/*.json and samples/LIDAR_TOP/*.pcd.bin).")],
    seed: SeedOpt = 0,
    duration: DurationOpt = 20.0,
    rate: Annotated[float, typer.Option("--rate", help="Keyframes per second (nuScenes: 2).")] = 2.0,
    lidar: LidarOpt = "hdl32e",
    min_points: Annotated[int, typer.Option("--min-points", help="Annotate only objects with at least this many LiDAR points.")] = 0,
    progress: ProgressOpt = None,
) -> None:
    """Export a scenario as a nuScenes-format dataroot (loads with nuscenes-devkit, version v1.0-mini)."""
    check_scenario_options(scenario, duration, rate, lidar, seed)
    if min_points < 0:
        fail("--min-points must be >= 0")
    if not dataroot.strip():  # it had exported into the current folder
        fail("DATAROOT: empty path; give a folder")
    root = Path(dataroot)
    if root.exists() and not root.is_dir():
        fail(f"{dataroot}: exists and is not a folder")
    if (root / "v1.0-mini").exists():
        fail(f"{dataroot}: already holds a v1.0-mini dataroot; choose an empty folder")
    from .export import export_scenario
    from .sensors import SENSORS
    from .world import make_scenario

    # the folder made and tried before the scans are cast (a minute for 60 s): it had failed only after them
    created = not root.exists()
    try:
        root.mkdir(parents=True, exist_ok=True)
        probe = root / f".jitterguard-write-test.{os.getpid()}"
        probe.touch()
        probe.unlink()
    except OSError as exc:
        fail(f"{dataroot}: cannot write: {exc.strerror or exc}")
    show = progress_on(progress)
    try:
        with sigterm_as_exit():  # from here on a stop removes the folder it made (the scenario takes seconds too)
            sc = make_scenario(scenario, seed, duration_s=duration, rate_hz=rate)
            sizes = export_scenario(sc, str(root), SENSORS[lidar](), seed, min_points=min_points,
                                    progress=lambda it: _bar(it, sc.num_frames, f"export {scenario}", show))
    except BaseException as exc:  # export_scenario removed what it wrote: no half-written dataroot is left
        if created:  # nor the folder it was made for (Ctrl-C or SIGTERM had left it, empty)
            with contextlib.suppress(OSError):
                root.rmdir()
        if not isinstance(exc, OSError):
            raise
        where = f" {exc.filename}" if exc.filename and os.fspath(exc.filename) != str(root) else ""
        fail(f"{dataroot}: cannot write{where}: {exc.strerror or exc}")
    print(json.dumps({"dataroot": str(root), "version": "v1.0-mini", "scenario": scenario, "seed": seed,
                      "tables": sizes}))


def bev_command(
    scenario: ScenarioArg,
    out: Annotated[str, typer.Option("--out", help="PNG file to write.")],
    seed: SeedOpt = 0,
    frame: Annotated[int, typer.Option("--frame", help="Frame index.")] = 50,
    duration: DurationOpt = 20.0,
    rate: Annotated[float, typer.Option("--rate", help="Frames per second.")] = 10.0,
    lidar: LidarOpt = "hdl32e",
    extent: Annotated[float, typer.Option("--extent", help="Half-width of the view in metres.")] = 40.0,
) -> None:
    """Render one ray-cast scan with its ground-truth boxes (colour = motion state) as a bird's-eye PNG."""
    check_scenario_options(scenario, duration, rate, lidar, seed)
    if not 5.0 <= extent <= 200.0:
        fail("--extent must be in [5, 200] metres")
    if not out.lower().endswith(".png"):
        fail("--out must name a .png file")
    refuse_foreign_file("--out", out, is_png, "a PNG")
    out_file("--out", out)  # before the ray-cast: it had failed only when the PNG was saved
    from .bev import render_bev
    from .lidar import cast_frame
    from .sensors import SENSORS
    from .world import make_scenario

    sc = make_scenario(scenario, seed, duration_s=duration, rate_hz=rate)
    if not 0 <= frame < sc.num_frames:
        fail(f"--frame must be in [0, {sc.num_frames - 1}] for {duration:g} s at {rate:g} Hz")
    spec = SENSORS[lidar]()
    res, gt = cast_frame(sc.frame(frame), spec, seed)
    title = f"{scenario} seed {seed}, frame {frame} (t = {frame / rate:.1f} s), {spec.name}: {len(res.points)} points"
    try:
        render_bev(gt, res.points, out, extent_m=extent, title=title)
    except OSError as exc:
        fail(f"--out: cannot write {out}: {exc.strerror or exc}")
    print(json.dumps({"out": out, "points": int(len(res.points)), "objects": gt.num_objects}))


def list_command() -> None:
    """List scenarios and LiDAR presets as JSON."""
    from .sensors import SENSORS
    from .world import SCENARIO_NAMES

    sensors = {k: {"name": s.name, "beams": s.num_beams, "azimuth_steps": s.azimuth_steps, "rate_hz": s.rate_hz,
                   "elevation_deg": [round(float(s.elevations_deg[0]), 2), round(float(s.elevations_deg[-1]), 2)]}
               for k, s in ((k, f()) for k, f in SENSORS.items())}
    print(json.dumps({"scenarios": list(SCENARIO_NAMES), "sensors": sensors}))


def register(app: typer.Typer, bench_app: typer.Typer) -> None:
    """Add ``sim`` (generate, export, bev, list) to the main app."""
    sim_app.command("generate")(generate_command)
    sim_app.command("export")(export_command)
    sim_app.command("bev")(bev_command)
    sim_app.command("list")(list_command)
    app.add_typer(sim_app, name="sim")
