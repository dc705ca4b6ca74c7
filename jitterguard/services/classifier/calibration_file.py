"""The calibration file: what ``jitterguard calibrate`` writes and the classifier reads with ``calibration: file``.

YAML, so a perception engineer can read and diff it::

    format: jitterguard-calibration/1
    digest: sha256:9f2c...                          # of every byte after this line
    range_bands_m: [20.0, 40.0]
    frame_interval_s: 0.1
    window: 10
    groups:
      vehicle:
        track_dof: 6.5
        along: {scale: {0-20: 0.41, ...}, scale_young: {...}, blocks: {...}, blocks_young: {...},
                correlation: 0.58, correlation_time_s: 0.07, variance_factor: 1.15}
        across: {...}
      ...
    source: {recording: ..., frames: ..., ...}     # free-form provenance, not read back

The content is :meth:`~.calibration.NoiseModel.to_mapping`; reading validates every number (finite, in range)
and names the first bad entry. The digest is there because a file cut short at a whole entry is still valid YAML
whose missing groups and axes keep the prior — a copy truncated on its way to the vehicle would load without a word.
A file without a digest line (written by hand) is read as it stands; one whose digest does not match is refused,
so a hand edit of a written file means deleting its digest line too. The only I/O of the calibration; the core
never reads files.
"""

from __future__ import annotations

import hashlib
import os
import stat
from pathlib import Path
from typing import Any

import yaml

from ...files import write_atomically
from .calibration import NoiseModel

FORMAT = "jitterguard-calibration/1"
MAX_BYTES = 1 << 20
"""A calibration file is a few kilobytes; anything above this is refused unread."""


class CalibrationFileError(ValueError):
    """A calibration file that cannot be used (the message is one line and names the file and the entry)."""


def dump_calibration(model: NoiseModel, *, window: int, source: dict[str, Any] | None = None) -> str:
    """The YAML text of a calibration file for ``model`` (``source``: provenance, written as given)."""
    data = model.to_mapping(window)
    if source:
        data["source"] = source
    body = yaml.safe_dump(data, sort_keys=False, default_flow_style=None, width=110)
    return f"format: {FORMAT}\n{DIGEST_KEY}: {_digest(body)}\n{body}"


DIGEST_KEY = "digest"


def _digest(body: str) -> str:
    """The digest line's value for the text after it."""
    return "sha256:" + hashlib.sha256(body.encode("utf-8")).hexdigest()


def _check_digest(text: str, claimed: object, where: str) -> None:
    """Refuse a written file whose bytes after its digest line are not those it was written with."""
    lines = text.splitlines(keepends=True)
    at = next((i for i, line in enumerate(lines) if line.startswith(f"{DIGEST_KEY}:")), None)
    if not isinstance(claimed, str) or at is None or _digest("".join(lines[at + 1:])) != claimed:
        raise CalibrationFileError(f"{where}: its digest does not match its content (cut short or edited; to use a"
                                   f" file edited by hand, delete its {DIGEST_KEY} line)")


def write_calibration(path: Path, model: NoiseModel, *, window: int, source: dict[str, Any] | None = None) -> None:
    """Write ``model`` to ``path`` (parents created), atomically: a classifier reading it meanwhile never sees half."""
    write_atomically(path, dump_calibration(model, window=window, source=source).encode("utf-8"))


def _other_version(fmt: object) -> bool:
    """Whether a file's ``format`` names this file type at another version (``jitterguard-calibration/N``): short,
    printable and ours, so quoting it back reveals nothing of a file that is not a calibration."""
    family = FORMAT.rsplit("/", 1)[0] + "/"
    return isinstance(fmt, str) and fmt.startswith(family) and len(fmt) <= len(family) + 8 and fmt.isprintable()


def parse_calibration(text: str, where: str = "calibration") -> NoiseModel:
    """A :class:`NoiseModel` from the text of a calibration file; :class:`CalibrationFileError` otherwise."""
    # Until the file says it is a calibration file, no error quotes it: a config write may name any path on the
    # classifier's host, and its reply must not become a way to read other files' lines.
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        at = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
        raise CalibrationFileError(f"{where}: not YAML ({getattr(exc, 'problem', None) or 'unreadable'}{at})") from None
    except RecursionError:  # [[[…]]] 20 000 deep: the parser's own recursion (it had been a traceback, exit 1)
        raise CalibrationFileError(f"{where}: not a calibration file (nested too deep to read)") from None
    except ValueError as exc:  # YAML's own conversions: more than 4300 digits, a date like 2024-02-30
        what = "a number too long to read" if "integer string conversion" in str(exc) else \
            "a value YAML cannot convert"
        raise CalibrationFileError(f"{where}: not a calibration file ({what})") from None
    if not isinstance(data, dict):
        raise CalibrationFileError(f"{where}: expected a mapping with format {FORMAT!r}")
    fmt = data.get("format")
    if fmt != FORMAT:
        if _other_version(fmt):  # ours, of another release: say so, not "no calibration file"
            raise CalibrationFileError(f"{where}: a calibration file of another version ({fmt!r}); this release reads"
                                       f" {FORMAT!r}: fit it again with `jitterguard calibrate`")
        raise CalibrationFileError(f"{where}: format must be {FORMAT!r}, not a calibration file")
    if DIGEST_KEY in data:
        _check_digest(text, data.pop(DIGEST_KEY), where)
    try:
        return NoiseModel.from_mapping(data)
    except ValueError as exc:
        raise CalibrationFileError(f"{where}: {exc}") from None
    except OverflowError:  # a 400-digit integer where a number is expected: no float holds it
        raise CalibrationFileError(f"{where}: a number too large for a float") from None
    except RecursionError:
        raise CalibrationFileError(f"{where}: a value nested too deep") from None


KERNEL_FILES = ("/proc/", "/sys/")
"""Where the kernel's own files live (Linux): never read as a calibration."""


def read_calibration(path: str | Path) -> NoiseModel:
    """Read and validate a calibration file; :class:`CalibrationFileError` (one line) when it cannot be used."""
    p = Path(path)
    try:
        # opened without blocking and read only if a regular file with something in it, at most MAX_BYTES of it: a
        # FIFO or a device must not stall the config queryable or fill memory, and the kernel's files (under /proc
        # and /sys: "regular", of size 0 or 4096 to stat, whatever they hold) are no calibration — read, their
        # YAML errors would describe their contents to whoever may write the config
        if os.path.realpath(p).startswith(KERNEL_FILES):
            raise CalibrationFileError(f"{p}: a kernel file, not a calibration file")
        fd = os.open(p, os.O_RDONLY | os.O_NONBLOCK)
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):  # judged before fdopen, which refuses a folder as "Is a directory: 3"
            os.close(fd)
            raise CalibrationFileError(f"{p}: {'a folder' if stat.S_ISDIR(st.st_mode) else 'not a regular file'},"
                                       " not a calibration file")
        with os.fdopen(fd, "rb") as fh:
            if st.st_size == 0:
                raise CalibrationFileError(f"{p}: empty, not a calibration file")
            raw = fh.read(MAX_BYTES + 1)
        if len(raw) > MAX_BYTES:
            raise CalibrationFileError(f"{p}: larger than {MAX_BYTES} bytes, not a calibration file")
        text = raw.decode("utf-8")
    except CalibrationFileError:
        raise
    except (OSError, ValueError) as exc:  # ValueError: a path no file system holds (a NUL byte, a lone surrogate)
        shown = str(p) if str(p).isprintable() else ascii(str(p))  # the reply must encode: no NUL, no surrogate
        raise CalibrationFileError(f"{shown}: cannot read: {exc.__class__.__name__}: {exc}") from None
    return parse_calibration(text, str(p))
