"""The classifier's parameters: the wire's :class:`~jitterguard.schemas.models.ClassifierConfig` (what the config
queryable reads and writes at run time) plus what only the process's start sets (limits, straggler timeout).

Presets (``paper``, ``authors``) are files beside the defaults (``jitterguard/config/classifier.<name>.param.yaml``);
applying one keeps every other field as it is.
"""

from __future__ import annotations

from pydantic import Field

from ...config import presets, preset_values
from ...schemas.models import ClassifierConfig
from ...schemas.wire import Limits
from ...stream_order import StreamLimits

PRESETS: dict[str, dict[str, object]] = {name: preset_values("classifier", name) for name in presets("classifier")}
"""Named config presets: the keys each sets."""


class ClassifierParams(ClassifierConfig):
    """``jitterguard classifier --config FILE``: every :class:`ClassifierConfig` field, and the process's own."""

    straggler_timeout_s: float = Field(
        0.05, gt=0.0, le=10.0, description="how long a closed frame waits for observations that have not arrived")
    limits: Limits = Field(default_factory=Limits, description="bounds on the work one message may cause")
    stream: StreamLimits = Field(
        default_factory=StreamLimits, description="how far a tracked frame may step from the last one taken; a"
        " discontinuity (the tracker restarted or rewound, a long gap) is followed only once successive frames"
        " confirm it")
    config_store: str | None = Field(
        None, min_length=1, description="JSON file keeping config writes across restarts (restored while the"
        " start-up config stays the same); none: writes last until the classifier stops (flag --config-store,"
        " env JG_CONFIG_STORE)")
    calibration_store: str | None = Field(
        None, min_length=1, description="file (.npz) keeping the online calibration across restarts, so a"
        " restarted classifier goes on calibrated (capped at 200 blocks of evidence); none: every start is cold"
        " (flag --calibration-store, env JG_CALIBRATION_STORE)")
    open_config_writes: bool = Field(
        False, description="accept config writes over Zenoh without a token when JG_API_TOKEN is unset; only where"
        " the router listens on loopback alone")

    def wire(self) -> ClassifierConfig:
        """The part that travels on the config queryable."""
        return ClassifierConfig.model_validate(self.model_dump(include=set(ClassifierConfig.model_fields)))
