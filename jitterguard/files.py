"""Files that a crash must never leave half-written (the classifier's stored config and calibration, the stack's
run summary)."""

from __future__ import annotations

import os
import stat
import tempfile
from pathlib import Path
from typing import Any


def not_a_file(path: str | os.PathLike[str]) -> str | None:
    """Why ``path`` is no file to read (``"file not found: P"``, ``"P is a folder, not a file"``), or None: a folder
    given for a file had been told "file not found", which sends the user looking for a file that is not missing."""
    p = Path(path)
    if p.is_file():
        return None
    return f"{p} is a folder, not a file" if p.is_dir() else f"file not found: {p}"


def not_a_folder(path: str | os.PathLike[str]) -> str | None:
    """Why ``path`` is no folder to read (``"no such folder: P"``, ``"P is a file, not a folder"``), or None."""
    p = Path(path)
    if p.is_dir():
        return None
    return f"{p} is a file, not a folder" if p.exists() else f"no such folder: {p}"


def write_atomically(path: str | os.PathLike[str], data: bytes, *, durable: bool = True) -> None:
    """Replace ``path`` with ``data`` so that a reader, or the file after a crash, is the old content or the new,
    never part of either: a temporary file in the same directory, renamed over the old one. ``durable`` also
    fsyncs the file before the rename and the directory after it (the new content survives a power loss).
    The file keeps the mode, and where this process may give them the owner and group, of the one it replaces
    (``root:jitterguard 0640`` stays so), or a new one gets the umask's mode (``mkstemp``'s 0600 had made a
    calibration file unreadable to the ``jitterguard`` user the deployment runs the classifier as, and an eval's
    plots unlike its metrics beside them). A symlink stays one: the file it names is replaced. Creates the
    directory; raises ``OSError``."""
    target = Path(os.path.realpath(path))  # through a symlink the file it names is replaced, the link kept
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
    try:
        _take_over_permissions(tmp, target)
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            if durable:
                f.flush()
                os.fsync(f.fileno())
        os.replace(tmp, target)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise
    if durable:
        dir_fd = os.open(target.parent, os.O_RDONLY)
        try:
            os.fsync(dir_fd)
        finally:
            os.close(dir_fd)


def save_figure(fig: Any, path: str | os.PathLike[str], **savefig_kwargs: Any) -> None:
    """Save a matplotlib figure through :func:`write_atomically` (the format from the suffix, PNG without one):
    ``savefig`` onto the path itself truncates an earlier picture first, so a run stopped or failing mid-write
    (Ctrl-C, a full disk) had left a broken PNG where a good one was. Raises ``OSError``."""
    import io

    buf = io.BytesIO()
    fig.savefig(buf, format=Path(path).suffix[1:].lower() or "png", **savefig_kwargs)
    write_atomically(path, buf.getvalue(), durable=False)


def _take_over_permissions(tmp: str, target: Path) -> None:
    """Give ``tmp`` the permission bits, owner and group of ``target`` (as far as this process may: the group
    alone, or neither), or — no ``target`` yet — 0666 less the umask."""
    try:
        st = target.stat()
    except OSError:
        os.chmod(tmp, 0o666 & ~_umask())
        return
    for uid in (st.st_uid, -1):  # the owner needs root; a member may still give the file its group
        try:
            os.chown(tmp, uid, st.st_gid)
            break
        except OSError:
            continue
    os.chmod(tmp, stat.S_IMODE(st.st_mode))  # after chown, which may clear set-id bits


def _umask() -> int:
    """The process's umask, read without changing it where Linux tells it (``os.umask`` can only set it: reading
    it that way would change it for a moment for every thread)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    except (OSError, ValueError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask
