"""jitterguard: tell real motion from perception jitter in LiDAR stacks (uncertainty-aware CenterPoint +
a two-sample z-test motion classifier), as a pipeline of Zenoh services."""

__version__ = "0.1.0"
