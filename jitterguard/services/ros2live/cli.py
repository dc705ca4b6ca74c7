"""``jitterguard ros2-in`` / ``ros2-out``: a live ROS 2 LiDAR topic into the pipeline, and its tracked objects back,
through zenoh-bridge-ros2dds."""

from __future__ import annotations

from typing import Annotated

import typer

from ...cli_common import ConnectOpt, ListenOpt, LogLevelOpt, NsOpt, ZenohConfigOpt, fail, parse_float, zenoh_options

EXAMPLES = """
Examples:\n
  zenoh-bridge-ros2dds -m client -e tcp/127.0.0.1:7447 &      # the vehicle's ROS 2 topics onto jitterguard's router\n
  jitterguard ros2-in --points-topic /sensing/lidar/top/pointcloud_raw_ex --pose-topic /tf\n
  jitterguard ros2-in --points-topic /points --pose-topic /localization/kinematic_state\n
  jitterguard ros2-in --points-topic /points --no-pose             # a sensor that does not move
"""
TF_TYPE = "tf2_msgs/msg/TFMessage"
ODOMETRY_TYPE = "nav_msgs/msg/Odometry"


def topic_option(flag: str, text: str) -> str:
    """A ROS 2 topic name a flag gives, or a one-line refusal naming the flag (exit 2)."""
    from .scans_in import check_topic

    try:
        return check_topic(flag, text)
    except ValueError as exc:
        fail(str(exc))


def register(app: typer.Typer, bench_app: typer.Typer) -> None:
    @app.command("ros2-in", help=(
        "Publish a live ROS 2 PointCloud2 topic on jitterguard's `points`, posed by /tf or an odometry topic, as"
        " zenoh-bridge-ros2dds carries ROS 2 topics into Zenoh (key = topic without its leading '/', payload = the"
        " message's CDR bytes). Scans are turned into base_link's axes where their mount is a static link, as a"
        " bag's are.\n\n" + EXAMPLES))
    def ros2_in_cmd(
        points_topic: Annotated[str, typer.Option("--points-topic", help="The sensor_msgs/msg/PointCloud2 topic.")]
        = "/sensing/lidar/top/pointcloud",
        pose_topic: Annotated[str, typer.Option("--pose-topic", help="/tf (with /tf_static), or a nav_msgs/Odometry"
                                                " or geometry_msgs Pose(WithCovariance)Stamped topic (with"
                                                " /tf_static for the sensor's mount).")] = "/tf",
        pose_type: Annotated[str | None, typer.Option("--pose-type", help="The pose topic's type; default: "
                                                      f"{TF_TYPE} for a topic named tf, else {ODOMETRY_TYPE}.")] = None,
        no_pose: Annotated[bool, typer.Option("--no-pose", help="Publish every scan at the identity pose (a sensor"
                                              " that does not move).")] = False,
        key_prefix: Annotated[str, typer.Option("--key-prefix", help="The bridge's namespace (its -n / "
                                                "`namespace`), if it has one.")] = "",
        tf_wait_s: Annotated[str, typer.Option("--tf-wait-s", help="How long a scan waits for the poses to reach its"
                                               " stamp before it is posed at the newest one (0-1 s).")] = "0.1",
        ns: NsOpt = "default",
        zenoh_config: ZenohConfigOpt = None,
        connect: ConnectOpt = None,
        listen: ListenOpt = None,
        log_level: LogLevelOpt = "INFO",
    ) -> None:
        from ..replay.sources.ros_types import POSE_TYPES

        points_topic = topic_option("--points-topic", points_topic)
        pose_topic = topic_option("--pose-topic", pose_topic)
        wait = parse_float("--tf-wait-s", tf_wait_s, 0.0, 1.0)
        if no_pose:
            kind = None
        else:
            kind = pose_type or (TF_TYPE if pose_topic.rstrip("/").endswith("/tf") else ODOMETRY_TYPE)
            if kind not in (TF_TYPE, *POSE_TYPES):
                fail(f"--pose-type: {kind!r} cannot pose a scan (use {TF_TYPE} or one of {', '.join(POSE_TYPES)})")
        opts = zenoh_options(ns, zenoh_config, connect, listen)

        from ...runtime import setup_logging
        from .in_service import Ros2InService

        setup_logging(log_level)
        service = Ros2InService(opts, points_topic=points_topic, pose_topic=None if no_pose else pose_topic,
                                pose_type=kind, key_prefix=key_prefix, tf_wait_s=wait)
        service.log.info("publishing %s (Zenoh key %s) on %s, posed by %s", points_topic, service.cloud_key,
                         f"jg/{opts.ns}/points", service.pose_key or "nothing (identity)")
        service.run_forever()

    @app.command("ros2-out", help=(
        "Put the classifier's objects on a live ROS 2 topic as autoware_perception_msgs/msg/TrackedObjects (the"
        " conversion of `record --ros2`: is_stationary from the classifier, static objects with zero velocity and"
        " their window-mean pose), as zenoh-bridge-ros2dds carries Zenoh keys into ROS 2 (key = the topic without"
        " its leading '/', payload = CDR).\n\n"
        "Examples:\n\n  jitterguard ros2-out                       # /perception/object_recognition/tracking/objects\n"))
    def ros2_out_cmd(
        topic: Annotated[str, typer.Option("--topic", help="The TrackedObjects topic (Autoware's prediction reads"
                                           " this one).")] = "/perception/object_recognition/tracking/objects",
        key_prefix: Annotated[str, typer.Option("--key-prefix", help="The bridge's namespace (its -n / "
                                                "`namespace`), if it has one.")] = "",
        ns: NsOpt = "default",
        zenoh_config: ZenohConfigOpt = None,
        connect: ConnectOpt = None,
        listen: ListenOpt = None,
        log_level: LogLevelOpt = "INFO",
    ) -> None:
        topic = topic_option("--topic", topic)
        opts = zenoh_options(ns, zenoh_config, connect, listen)

        from ...runtime import setup_logging
        from .out_service import Ros2OutService

        setup_logging(log_level)
        service = Ros2OutService(opts, topic=topic, key_prefix=key_prefix)
        service.log.info("putting jg/%s/objects on %s (Zenoh key %s)", opts.ns, topic, service.key)
        service.run_forever()
