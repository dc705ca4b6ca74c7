"""ROS 2 interop: Autoware's ``autoware_perception_msgs`` definitions shipped with the package (``msg/``), the type
store that knows them (:mod:`.types`), and the conversions between the wire contract and the ROS 2 messages
(:mod:`.autoware`). rosbags is imported when a type store is built, so importing this package costs nothing."""
