"""The replay publisher: recordings (synthetic, nuScenes, KITTI, PCD, ROS 2 bags) onto ``jg/{ns}/points``
or ``jg/{ns}/detections`` at the recorded rate times ``--rate``.

Layout: ``sources/`` are pure readers (files in, frames out), ``pacing`` and ``runner`` are the pure replay
logic, ``publisher`` is the thin Zenoh adapter, ``cli`` and ``bench`` the commands.
"""
