"""Where a recording goes when its name is taken."""

from __future__ import annotations

from pathlib import Path


def next_free_path(path: Path) -> Path:
    """``path`` if free, else the first free of ``stem.1.suffix``, ``stem.2.suffix``, ... (a supervised recorder
    that restarts must not overwrite, nor refuse to write, the recording of its previous run)."""
    if not path.exists():
        return path
    i = 1
    while True:
        cand = path.with_name(f"{path.stem}.{i}{path.suffix}")
        if not cand.exists():
            return cand
        i += 1
