"""Bridges out of jitterguard: the pipeline's per-frame messages joined (:mod:`.joiner`) and handed to a sink
(:mod:`.service`) — the Foxglove server and MCAP recorder, the ROS 2 bag recorder."""
