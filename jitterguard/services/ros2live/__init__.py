"""Live ROS 2 through zenoh-bridge-ros2dds: a ``sensor_msgs/PointCloud2`` topic and its poses in, published on
``points`` (``ros2-in``); the classifier's ``objects`` out as Autoware's ``TrackedObjects`` (``ros2-out``)."""
