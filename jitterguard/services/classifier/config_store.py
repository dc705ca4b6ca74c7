"""The classifier's config on disk, so that a write survives the classifier's restart.

One JSON file (``--config-store``; ``jitterguard up`` puts it in the stack's run directory) holds the config in
force and the config the classifier was started with (its flags). At start, the stored config is restored only
if the flags are still the same: a crash or a supervisord restart keeps what an operator set over HTTP, while
an operator who restarts with different flags gets what the flags say. A write goes to a temporary file in the
same directory, is fsync'ed and renamed over the old one (then the directory is fsync'ed): a crash leaves the
old file or the new one, never half of one. The classifier stores a write *before* applying it, and refuses
the write if it cannot store it, so what is in force and what a restart restores never differ.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

from pydantic import ValidationError

from ...files import write_atomically
from ...schemas.models import ClassifierConfig

FORMAT = "jitterguard.classifier-config/1"


class ConfigStore:
    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        self.damaged = False
        """Whether the last :meth:`load` found a file it could not use (unreadable, not this format, invalid): the
        writes it held are lost, which the classifier logs as a warning and counts (``config_store_errors``) — not
        as the info of a first start or of changed flags."""

    def load(self, started_with: ClassifierConfig) -> tuple[ClassifierConfig | None, str]:
        """The stored config if it belongs to a classifier started as this one (else None), and why."""
        self.damaged = True
        try:
            doc = json.loads(self.path.read_text(encoding="utf-8"))
        except FileNotFoundError:
            self.damaged = False
            return None, f"no stored config at {self.path}"
        except (OSError, ValueError) as exc:
            return None, f"stored config {self.path} is unreadable ({exc}); starting from the flags"
        if not isinstance(doc, dict) or doc.get("format") != FORMAT:
            return None, f"stored config {self.path} is not a {FORMAT} file; starting from the flags"
        try:
            base = ClassifierConfig.model_validate(doc.get("started_with"))
            config = ClassifierConfig.model_validate(doc.get("config"))
        except ValidationError as exc:
            return None, f"stored config {self.path} is invalid ({exc.errors()[0]['msg']}); starting from the flags"
        self.damaged = False
        if base != started_with:
            return None, f"the flags changed since {self.path} was written; starting from the flags"
        return config, f"config restored from {self.path}"

    def save(self, started_with: ClassifierConfig, config: ClassifierConfig) -> None:
        """Write atomically (temp file, fsync, rename, fsync the directory); raises ``OSError``."""
        doc = {"format": FORMAT, "started_with": started_with.model_dump(mode="json"),
               "config": config.model_dump(mode="json")}
        write_atomically(self.path, json.dumps(doc, indent=2, sort_keys=True).encode() + b"\n")
