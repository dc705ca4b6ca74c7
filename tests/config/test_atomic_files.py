"""Files written whole-or-not-at-all keep the permissions a user expects (``mkstemp``'s 0600 had made a calibration
file unreadable to the ``jitterguard`` user the deployment runs the classifier as)."""

from __future__ import annotations

import os
import stat
from pathlib import Path

from jitterguard.files import write_atomically


def test_a_new_file_gets_the_umasks_mode_and_a_replaced_one_keeps_its_own(tmp_path: Path) -> None:
    old = os.umask(0o022)
    try:
        fresh = tmp_path / "calibration.yaml"
        write_atomically(fresh, b"a: 1\n")
        assert stat.S_IMODE(fresh.stat().st_mode) == 0o644
        os.umask(0o077)
        write_atomically(tmp_path / "private.yaml", b"x")
        assert stat.S_IMODE((tmp_path / "private.yaml").stat().st_mode) == 0o600
        fresh.chmod(0o640)
        write_atomically(fresh, b"a: 2\n")
        assert stat.S_IMODE(fresh.stat().st_mode) == 0o640 and fresh.read_bytes() == b"a: 2\n"
    finally:
        os.umask(old)
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temporary file left


def test_a_replaced_file_keeps_its_group_and_a_symlink_stays_one(tmp_path: Path) -> None:
    """``root:jitterguard 0640`` (docs/deployment.md's shared files) had become ``root:root``, unreadable to the
    deployment's user; a symlink had been replaced by a regular file, its target left stale."""
    real = tmp_path / "real.yaml"
    real.write_bytes(b"old")
    os.chown(real, 0, 4242) if os.geteuid() == 0 else None
    real.chmod(0o640)
    link = tmp_path / "link.yaml"
    link.symlink_to(real)
    write_atomically(link, b"new")
    assert link.is_symlink() and real.read_bytes() == b"new"
    st = real.stat()
    assert stat.S_IMODE(st.st_mode) == 0o640
    if os.geteuid() == 0:
        assert st.st_gid == 4242
