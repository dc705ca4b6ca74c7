"""Shared service runtime: Zenoh config from flags, the Service base class, counters, logging."""

from .service import Counters, Service, setup_logging
from .zenoh_config import ENV_CONFIG, ZenohOptions, build_config, free_tcp_port, loopback_options, open_session

__all__ = ["Counters", "Service", "setup_logging", "ENV_CONFIG", "ZenohOptions", "build_config",
           "free_tcp_port", "loopback_options", "open_session"]
