"""``jitterguard record``: the pipeline's frames written to a ROS 2 bag for Autoware (:mod:`.rosbag`)."""
