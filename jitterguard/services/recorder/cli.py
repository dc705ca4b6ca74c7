"""``jitterguard record --ros2 DIR``: write the running pipeline to a ROS 2 bag for Autoware."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from ...cli_common import ConnectOpt, ListenOpt, LogLevelOpt, NsOpt, ZenohConfigOpt, fail, new_dir, zenoh_options

EXAMPLES = """
Examples:\n
  jitterguard record --ros2 run_bag                      # until Ctrl-C; then: ros2 bag info run_bag\n
  jitterguard replay run_bag --topic /perception/object_recognition/detection/objects --pose-topic /tf\n
  jitterguard up --record-ros2 run_bag                   # with the whole stack
"""


def register(app: typer.Typer, bench_app: typer.Typer) -> None:
    @app.command("record", help=(
        "Record the pipeline to a ROS 2 bag (MCAP storage) with Autoware's perception topics: DetectedObjects,"
        " TrackedObjects (is_stationary from the classifier; static objects with zero velocity and the window-mean"
        " pose), PointCloud2 and /tf.\n\n" + EXAMPLES))
    def record_cmd(
        ros2: Annotated[str, typer.Option("--ros2", help="Folder of the new rosbag2 (must not exist).")],
        ns: NsOpt = "default",
        zenoh_config: ZenohConfigOpt = None,
        connect: ConnectOpt = None,
        listen: ListenOpt = None,
        points: Annotated[bool, typer.Option("--points/--no-points", help="Record the scans as PointCloud2.")] = True,
        points_layout: Annotated[str, typer.Option("--points-layout", help="The scans' PointCloud2 layout: 'xyzirc',"
                                                   " Autoware's PointXYZIRC (float32 x, y, z; uint8 intensity, uint8"
                                                   " return_type, uint16 channel: what its LiDAR pipeline takes), or"
                                                   " 'float32', every wire column float32 as sent.")] = "xyzirc",
        number_if_exists: Annotated[bool, typer.Option("--number-if-exists", help="If the folder exists, write FOLDER.1, FOLDER.2, ... instead of failing (for supervised restarts).")] = False,
        log_level: LogLevelOpt = "INFO",
    ) -> None:
        from ..bridge.paths import next_free_path

        if not ros2.strip():  # Path("") is the current folder: "--ros2:  exists", or a bag in ./.1
            fail("--ros2: empty path; give a folder")
        path = Path(ros2)
        if path.exists():
            if not number_if_exists:
                fail(f"--ros2: {ros2} exists (rosbag2 writes a new folder)")
            path = next_free_path(path)
        from ...ros2.points import LAYOUTS

        if points_layout not in LAYOUTS:
            fail(f"--points-layout: {points_layout!r} is not one of {', '.join(LAYOUTS)}")
        new_dir("--ros2", path)  # made and removed: a folder test passes /proc, where rosbags' mkdir then failed
        opts = zenoh_options(ns, zenoh_config, connect, listen)

        from ...runtime import setup_logging
        from .rosbag import Rosbag2Sink, RosbagError
        from .service import RecorderService

        setup_logging(log_level)
        try:
            sink = Rosbag2Sink(path, points=points, points_layout=points_layout)
        except RosbagError as exc:
            fail(f"--ros2: {exc}")
        try:
            service = RecorderService(opts, sink, points=points)
        except ValueError as exc:  # the bag is made with its first frame: there is none to close or remove
            fail(str(exc))
        service.log.info("recording a ROS 2 bag into %s", path)
        service.run_forever()
