"""Foxglove: the pipeline live over the Foxglove WebSocket protocol and recorded to MCAP (the foxglove-sdk package)."""
