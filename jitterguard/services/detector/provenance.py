"""What a weights file has seen of a real dataroot: the one answer ``eval-detector`` and ``eval`` give.

A detector figure on real data counts only on scenes whose labels never trained the weights (issue 16: never train
and test on frames of one scene) and says so when the weights were adapted on the scored scans (test-time
adaptation). The weights' metadata records it: ``source`` (what ``train`` read: a nuScenes dataroot with its
``split``/``val_split``, or the last ``holdout_last`` key frames of every scene held out), ``unlabelled_scans``
(what ``adapt`` read, labels never), and ``init_provenance`` — the same records of the weights a ``train --init``
started from, so a fine-tune of nuScenes-trained weights on synthetic scans still says what its network saw.

Pure: metadata and scene names in, an answer out; the devkit's split tables are read only for split-trained weights.
"""

from __future__ import annotations

import re
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

PROVENANCE_KEYS = ("source", "unlabelled_scans", "init_provenance")
"""The metadata that says what data a network saw; ``train --init`` carries the init weights' under
``init_provenance``."""
MAX_LINEAGE = 64
"""Generations read at most (a hand-edited file could nest without end)."""


def init_provenance(meta: dict[str, Any]) -> dict[str, Any] | None:
    """What ``train --init`` keeps of the init weights' metadata (None when it records nothing)."""
    kept = {k: meta[k] for k in PROVENANCE_KEYS if meta.get(k)}
    return kept or None


def lineage(meta: dict[str, Any]) -> Iterator[dict[str, Any]]:
    """``meta``, then the provenance of the weights it was fine-tuned from, and so on back."""
    node: Any = meta
    for _ in range(MAX_LINEAGE):
        if not isinstance(node, dict):
            return
        yield node
        node = node.get("init_provenance")


def _recorded(a: Any) -> Path | None:
    """A path as the metadata records it (``#scene`` dropped), resolved; None when none is recorded."""
    return Path(str(a).split("#", 1)[0]).resolve() if a else None


def _same_path(a: Any, b: str | Path) -> bool:
    return _recorded(a) == Path(b).resolve()


def seen_scenes(meta: dict[str, Any], dataroot: str | Path, scenes: Sequence[str]) -> list[str]:
    """The ``scenes`` of ``dataroot`` whose labels trained the weights (theirs or an ancestor's): every scene when
    trained with held-out key frames (the held-out tail is still the scene), a scene of the recorded ``split`` or
    ``val_split`` otherwise (the validation scenes' labels fit the recalibration); every scene when those splits
    cannot be read (no devkit): unknown counts as seen."""
    seen: set[str] = set()
    for node in lineage(meta):
        source = node.get("source")
        if not isinstance(source, dict) or not _same_path(source.get("nuscenes"), dataroot):
            continue
        if not source.get("split"):
            return list(scenes)
        try:
            from .data_nuscenes import official_split

            for name in (source["split"], source.get("val_split")):
                if name:
                    seen |= set(official_split(str(name)))
        except Exception:  # noqa: BLE001 - the devkit missing or a split it does not know: cannot tell, say seen
            return list(scenes)
    return [s for s in scenes if s in seen]


def _inside(a: Any, root: str | Path) -> bool:
    """Whether the recorded path ``a`` (``#scene`` dropped) is ``root`` or lies under it, both resolved."""
    path, top = _recorded(a), Path(root).resolve()
    return path is not None and (path == top or top in path.parents)


def adapted_on_scans(meta: dict[str, Any], recording: str | Path) -> bool:
    """Whether the weights (or an ancestor) were adapted on scans of ``recording`` (a folder or file; for a nuScenes
    dataroot any of its scenes, or any folder or file inside it — ``adapt --scans DATAROOT/samples/LIDAR_TOP`` reads
    the very key frames ``eval-detector --nuscenes DATAROOT`` scores): scoring them there is test-time adaptation,
    not a cross-scene test."""
    return any(isinstance(rec, dict) and _inside(rec.get("recording"), recording)
               for node in lineage(meta) for rec in (node.get("unlabelled_scans") or []))


TRAIN_SEEDS_FLAG = re.compile(r"--train-seeds[ =](\S+)")


def trained_seeds(meta: dict[str, Any]) -> set[int]:
    """The synthetic seeds whose labelled scans trained a weights file: its ``source.train_seeds`` along its lineage,
    and every ``--train-seeds`` of the recipe or command it records (the shipped files were fine-tuned in several
    steps, each on other seeds). A recalibration or a hold-out score on any of them would grade the network on
    scans it learnt: ``recalibrate-detector`` and ``eval-detector`` refuse them."""
    from ...cli_common import seed_range  # the CLI's own reading of "0-49,60"

    texts: list[str] = []
    for node in lineage(meta):
        source = node.get("source")
        if isinstance(source, dict) and isinstance(source.get("train_seeds"), str):
            texts.append(source["train_seeds"])
        for key in ("recipe", "command"):
            texts += TRAIN_SEEDS_FLAG.findall(str(node.get(key, "")))
    seeds: set[int] = set()
    for text in texts:
        try:
            seeds |= seed_range(text.strip("'\",]"))
        except ValueError:  # a hand-edited record: what cannot be read cannot be checked
            continue
    return seeds


def seeds_refusal(flag: str, asked: Sequence[int], meta: dict[str, Any]) -> str | None:
    """The one-line refusal of ``asked`` seeds that trained the weights (:func:`trained_seeds`), or None."""
    taken = sorted(set(asked) & trained_seeds(meta))
    if not taken:
        return None
    shown = ", ".join(map(str, taken[:5])) + (" …" if len(taken) > 5 else "")
    return (f"{flag}: seed(s) {shown} trained these weights (their recorded --train-seeds); give seeds the network"
            " never learnt from")
