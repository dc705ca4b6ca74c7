"""Live ROS 2 scans in: a ``sensor_msgs/PointCloud2`` topic and its poses bridged into Zenoh, published on ``points``."""
