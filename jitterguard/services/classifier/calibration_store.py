"""The online calibration on disk, so that a restarted classifier does not decide its first seconds uncalibrated.

Until a track's window has filled, the online calibration has nothing to learn from; a classifier that starts
cold takes the detector's variances as they are, and on real scans those can be far off (the shipped
detector's were 2× too small in σ before their score-binned recalibration) — the first seconds after every
restart call parked cars moving (on nuScenes scene-0523, `clean`, 20 of the 33 false
rows fall in the first 5 s). With ``calibration_store`` the service writes what the estimator has pooled
(:meth:`~.calibration.OnlineCalibration.state`, an ``.npz`` of plain arrays, no pickle) at most every
:data:`SAVE_PERIOD_S` and when it stops, and a new process goes on from it — capped at
:data:`RESTORE_MAX_BLOCKS` effective blocks, so that a detector swapped between two runs is outvoted by the new
data within seconds rather than a half-life. A file that cannot be used (another format, other range bands,
damaged) is ignored with the reason logged: the classifier then starts cold, as without a store.
"""

from __future__ import annotations

import io
import os
from pathlib import Path

import numpy as np

from ...files import write_atomically
from .calibration import OnlineCalibration

FORMAT = "jitterguard.classifier-calibration/1"
SAVE_PERIOD_S = 10.0
"""Wall-clock seconds between two writes of a changed calibration (a write is ~0.5 MB)."""
RESTORE_MAX_BLOCKS = 200.0
"""The most effective blocks a restart takes over (the prior's 20 pseudo-blocks per level are 1/10 of it)."""


class CalibrationStore:
    """One ``.npz`` file holding an :class:`OnlineCalibration`'s pooled state."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)

    def load_into(self, online: OnlineCalibration) -> str:
        """Restore ``online`` from the file if it can be used; returns what happened, for the log."""
        try:
            with np.load(self.path, allow_pickle=False) as z:
                state = {k: z[k] for k in z.files}
        except FileNotFoundError:
            return f"no stored calibration at {self.path}; starting cold"
        except Exception as exc:  # noqa: BLE001 - any damage (a truncated zip, a CRC error, an .npy) starts cold:
            # it had raised BadZipFile or TypeError from the constructor, and supervisord restarted into the crash
            return f"stored calibration {self.path} is unreadable ({type(exc).__name__}: {exc}); starting cold"
        if str(state.get("format", "")) != FORMAT:
            return f"stored calibration {self.path} is not a {FORMAT} file; starting cold"
        try:
            blocks = online.restore(state, max_blocks=RESTORE_MAX_BLOCKS)
        except (ValueError, KeyError, TypeError, IndexError) as exc:
            return f"stored calibration {self.path} does not fit this classifier ({exc}); starting cold"
        return f"calibration restored from {self.path} ({blocks:.0f} effective blocks)"

    def save(self, state: dict[str, np.ndarray]) -> None:
        """Write a :meth:`OnlineCalibration.state` atomically; raises ``OSError``."""
        buf = io.BytesIO()
        np.savez(buf, format=np.asarray(FORMAT), **state)
        write_atomically(self.path, buf.getvalue())
