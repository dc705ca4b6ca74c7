"""``jitterguard ros2-in`` / ``ros2-out``: a live ROS 2 LiDAR topic into the pipeline, and its tracked objects back,
through zenoh-bridge-ros2dds or straight from and to ROS 2 nodes on rmw_zenoh."""

from __future__ import annotations

from typing import TYPE_CHECKING, Annotated

import typer

from ...cli_common import (ConnectOpt, ListenOpt, LogLevelOpt, NsOpt, ZenohConfigOpt, check_endpoints, fail,
                           parse_float, parse_int, zenoh_options)
from ...runtime.zenoh_config import ZenohOptions

if TYPE_CHECKING:
    from .ros_keys import RosNaming

EXAMPLES = """
Examples:\n
  zenoh-bridge-ros2dds -m client -e tcp/127.0.0.1:7447 &      # the vehicle's ROS 2 topics onto jitterguard's router\n
  jitterguard ros2-in --points-topic /sensing/lidar/top/pointcloud_raw_ex --pose-topic /tf\n
  jitterguard ros2-in --points-topic /points --pose-topic /localization/kinematic_state\n
  jitterguard ros2-in --points-topic /points --no-pose             # a sensor that does not move\n
  jitterguard ros2-in --middleware rmw_zenoh --ros-connect tcp/127.0.0.1:7447   # nodes on rmw_zenoh, via rmw_zenohd\n
  jitterguard ros2-in --objects-topic /perception/object_recognition/detection/objects   # Autoware's own boxes
"""
TF_TYPE = "tf2_msgs/msg/TFMessage"
DEFAULT_POINTS_TOPIC = "/sensing/lidar/top/pointcloud"
ODOMETRY_TYPE = "nav_msgs/msg/Odometry"


MiddlewareOpt = Annotated[str, typer.Option(
    "--middleware", help="How the ROS 2 system is on Zenoh: 'bridge' (zenoh-bridge-ros2dds: topic /a/b on key a/b)"
    " or 'rmw_zenoh' (ROS 2 nodes on rmw_zenoh: key DOMAIN/a/b/TYPE/HASH).")]
DomainIdOpt = Annotated[str, typer.Option("--domain-id", envvar="ROS_DOMAIN_ID",
                                          help="rmw_zenoh: the ROS domain ID (0-232; default $ROS_DOMAIN_ID, else 0).")]
KeyPrefixOpt = Annotated[str, typer.Option("--key-prefix", help="bridge: the bridge's namespace (its -n /"
                                           " `namespace`), if it has one.")]
RosDistroOpt = Annotated[str, typer.Option(
    "--ros-distro", envvar="ROS_DISTRO", help="rmw_zenoh: the ROS 2 distribution of the nodes (default $ROS_DISTRO,"
    " else jazzy); on humble, which has no type hashes, keys and graph tokens carry TypeHashNotSupported instead.")]
RosConnectOpt = Annotated[list[str] | None, typer.Option(
    "--ros-connect", help="The ROS 2 system's own Zenoh router (rmw_zenohd, or a bridge's), e.g. tcp/127.0.0.1:7447:"
    " the ROS 2 topics are read/put on a client session of it (repeatable), not on jitterguard's router.")]


def ros_side(middleware: str, domain_id: str, key_prefix: str, ros_connect: list[str] | None, ns: str, *,
             distro: str = "jazzy",
             names: tuple[str, str, str] = ("--middleware", "--domain-id", "--ros-distro"),
             ) -> tuple[RosNaming, ZenohOptions | None]:
    """The ROS 2 flags as the keys' naming and the ROS side's session options (None: the service's own session),
    or a one-line refusal naming the flag (exit 2; ``names``: how the caller's user gave the middleware, the
    domain ID and the distribution)."""
    from .ros_keys import DISTROS_WITHOUT_TYPE_HASHES, MAX_DOMAIN_ID, MIDDLEWARES, RosNaming, check_key_prefix

    if middleware not in MIDDLEWARES:
        fail(f"{names[0]}: {middleware!r} is not one of {', '.join(MIDDLEWARES)}")
    domain = parse_int(names[1], domain_id, 0, MAX_DOMAIN_ID)
    try:
        check_key_prefix("--key-prefix", key_prefix)
    except ValueError as exc:
        fail(str(exc))
    if middleware == "rmw_zenoh" and key_prefix.strip("/"):
        fail("--key-prefix: a bridge's namespace; rmw_zenoh keys have none (they start with the domain ID)")
    if not distro.isalpha() or not distro.islower():
        fail(f"{names[2]}: {distro!r} is not a ROS 2 distribution's name (humble, jazzy, kilted, rolling, ...)")
    naming = RosNaming(middleware, key_prefix, domain,  # type: ignore[arg-type]
                       type_hashes=distro not in DISTROS_WITHOUT_TYPE_HASHES)
    if not ros_connect:
        return naming, None
    check_endpoints(list(ros_connect))
    return naming, ZenohOptions(ns=ns, connect=tuple(ros_connect), mode="client")


def topic_option(flag: str, text: str) -> str:
    """A ROS 2 topic name a flag gives, or a one-line refusal naming the flag (exit 2)."""
    from .ros_keys import check_topic

    try:
        return check_topic(flag, text)
    except ValueError as exc:
        fail(str(exc))


def register(app: typer.Typer, bench_app: typer.Typer) -> None:
    @app.command("ros2-in", help=(
        "Publish a live ROS 2 PointCloud2 topic on jitterguard's `points`, posed by /tf or an odometry topic, as"
        " zenoh-bridge-ros2dds carries ROS 2 topics into Zenoh (key = topic without its leading '/', payload = the"
        " message's CDR bytes) or ROS 2 nodes on rmw_zenoh put them (--middleware rmw_zenoh). Scans are turned into"
        " base_link's axes where their mount is a static link, as a bag's are. With --objects-topic, the vehicle's own"
        " detector's DetectedObjects go on jitterguard's `detections` instead (for its tracker; no detector).\n\n"
        + EXAMPLES))
    def ros2_in_cmd(
        points_topic: Annotated[str | None, typer.Option("--points-topic", help="The sensor_msgs/msg/PointCloud2"
                                                         f" topic (default {DEFAULT_POINTS_TOPIC}).")] = None,
        objects_topic: Annotated[str | None, typer.Option(
            "--objects-topic", help="Instead of scans: an autoware_perception_msgs/msg/DetectedObjects topic (the"
            " vehicle's own detector, e.g. /perception/object_recognition/detection/objects), published on"
            " `detections`.")] = None,
        pose_topic: Annotated[str | None, typer.Option("--pose-topic", help="/tf (with /tf_static; the default),"
                                                       " or a nav_msgs/Odometry or geometry_msgs"
                                                       " Pose(WithCovariance)Stamped topic (with /tf_static for the"
                                                       " sensor's mount).")] = None,
        pose_type: Annotated[str | None, typer.Option("--pose-type", help="The pose topic's type; default: "
                                                      f"{TF_TYPE} for a topic named tf, else {ODOMETRY_TYPE}.")] = None,
        no_pose: Annotated[bool, typer.Option("--no-pose", help="Publish every scan at the identity pose (a sensor"
                                              " that does not move); refused with --pose-topic or --pose-type,"
                                              " which it would ignore.")] = False,
        middleware: MiddlewareOpt = "bridge",
        domain_id: DomainIdOpt = "0",
        key_prefix: KeyPrefixOpt = "",
        ros_distro: RosDistroOpt = "jazzy",
        ros_connect: RosConnectOpt = None,
        tf_wait_s: Annotated[str, typer.Option("--tf-wait-s", help="How long a scan waits for the poses to reach its"
                                               " stamp before it is posed at the newest one (0-1 s).")] = "0.1",
        ns: NsOpt = "default",
        zenoh_config: ZenohConfigOpt = None,
        connect: ConnectOpt = None,
        listen: ListenOpt = None,
        log_level: LogLevelOpt = "INFO",
    ) -> None:
        from ..replay.sources.ros_types import POSE_TYPES

        if points_topic is not None and objects_topic is not None:
            fail("--objects-topic takes the vehicle's detections in place of scans: give it or --points-topic")
        topic = (topic_option("--objects-topic", objects_topic) if objects_topic is not None
                 else topic_option("--points-topic", DEFAULT_POINTS_TOPIC if points_topic is None else points_topic))
        if no_pose and (pose_topic is not None or pose_type is not None):  # it had ignored them without a word
            fail(f"--no-pose publishes every scan at the identity pose: give it or"
                 f" {'--pose-topic' if pose_topic is not None else '--pose-type'}, not both")
        pose_topic = topic_option("--pose-topic", "/tf" if pose_topic is None else pose_topic)
        wait = parse_float("--tf-wait-s", tf_wait_s, 0.0, 1.0)
        if no_pose:
            kind = None
        else:
            kind = pose_type or (TF_TYPE if pose_topic.rstrip("/").endswith("/tf") else ODOMETRY_TYPE)
            if kind not in (TF_TYPE, *POSE_TYPES):
                fail(f"--pose-type: {kind!r} cannot pose a scan (use {TF_TYPE} or one of {', '.join(POSE_TYPES)})")
        opts = zenoh_options(ns, zenoh_config, connect, listen)
        naming, ros_opts = ros_side(middleware, domain_id, key_prefix, ros_connect, opts.ns, distro=ros_distro)

        from ...runtime import setup_logging
        from .in_service import Ros2InService

        setup_logging(log_level)
        from ...ros2.types import DETECTED_OBJECTS, POINTCLOUD2

        service = Ros2InService(opts, topic=topic, pose_topic=None if no_pose else pose_topic, pose_type=kind,
                                msgtype=POINTCLOUD2 if objects_topic is None else DETECTED_OBJECTS, naming=naming,
                                ros_opts=ros_opts, tf_wait_s=wait)
        service.log.info("publishing %s (Zenoh key %s) on %s, posed by %s", topic, service.in_key, service.out_key,
                         service.pose_key or "nothing (identity)")
        service.run_forever()

    @app.command("ros2-out", help=(
        "Put the classifier's objects on a live ROS 2 topic as autoware_perception_msgs/msg/TrackedObjects (the"
        " conversion of `record --ros2`: is_stationary from the classifier, static objects with zero velocity and"
        " their window-mean pose), as zenoh-bridge-ros2dds carries Zenoh keys into ROS 2 (key = the topic without"
        " its leading '/', payload = CDR), or for ROS 2 nodes on rmw_zenoh (--middleware rmw_zenoh: the key with the"
        " type's hash, the attachment rmw_zenoh's subscriptions require).\n\n"
        "Examples:\n\n  jitterguard ros2-out                       # /perception/object_recognition/tracking/objects\n"
        "  jitterguard ros2-out --middleware rmw_zenoh --ros-connect tcp/127.0.0.1:7447\n"))
    def ros2_out_cmd(
        topic: Annotated[str, typer.Option("--topic", help="The TrackedObjects topic (Autoware's prediction reads"
                                           " this one).")] = "/perception/object_recognition/tracking/objects",
        middleware: MiddlewareOpt = "bridge",
        domain_id: DomainIdOpt = "0",
        key_prefix: KeyPrefixOpt = "",
        ros_distro: RosDistroOpt = "jazzy",
        ros_connect: RosConnectOpt = None,
        ns: NsOpt = "default",
        zenoh_config: ZenohConfigOpt = None,
        connect: ConnectOpt = None,
        listen: ListenOpt = None,
        log_level: LogLevelOpt = "INFO",
    ) -> None:
        topic = topic_option("--topic", topic)
        opts = zenoh_options(ns, zenoh_config, connect, listen)
        naming, ros_opts = ros_side(middleware, domain_id, key_prefix, ros_connect, opts.ns, distro=ros_distro)

        from ...runtime import setup_logging
        from .out_service import Ros2OutService

        setup_logging(log_level)
        service = Ros2OutService(opts, topic=topic, naming=naming, ros_opts=ros_opts)
        service.log.info("putting jg/%s/objects on %s (Zenoh key %s)", opts.ns, topic, service.key)
        service.run_forever()
