"""One seam between the wire and the cores: the live services and the offline evaluator read and write the hot
messages with the same functions, imported from one place (``jitterguard.schemas``), and nothing outside
``schemas/`` takes a hot message apart or puts one together by hand."""

from __future__ import annotations

import ast
import importlib
from pathlib import Path

import pytest

import jitterguard
from jitterguard import schemas
from jitterguard.schemas import wire

ROOT = Path(jitterguard.__file__).parent
SEAM = [name for name in dir(wire) if name.startswith(("read_", "write_")) and callable(getattr(wire, name))]
USERS = {  # module -> the read/write functions it must use
    "jitterguard.services.tracker.service": {"read_detected_objects"},
    "jitterguard.services.tracker.adapter": {"write_track_observations", "write_tracked_objects"},
    "jitterguard.services.classifier.adapter": {"read_track_observations", "read_tracked_objects",
                                                "write_tracked_objects", "write_motion_states"},
    "jitterguard.services.detector.adapter": {"write_detected_objects"},
    "jitterguard.eval.pipeline": {"read_detected_objects"},
}


def test_every_hot_message_has_one_read_and_one_write() -> None:
    for message in ("detected_objects", "tracked_objects", "track_observations"):
        assert f"read_{message}" in SEAM and f"write_{message}" in SEAM
        assert getattr(schemas, f"read_{message}") is getattr(wire, f"read_{message}")  # the package's name for it


@pytest.mark.parametrize("module", sorted(USERS))
def test_services_and_the_evaluator_call_the_very_same_functions(module: str) -> None:
    mod = importlib.import_module(module)
    for name in USERS[module]:
        assert getattr(mod, name) is getattr(wire, name), f"{module}.{name} is not jitterguard.schemas.wire.{name}"


def test_the_evaluator_runs_the_services_adapters() -> None:
    """What is measured offline is what runs live: the evaluator holds the services' adapter code itself."""
    from jitterguard.eval import pipeline
    from jitterguard.services.classifier import adapter as classifier_adapter
    from jitterguard.services.tracker import adapter as tracker_adapter

    assert pipeline.ClassifierAdapter is classifier_adapter.ClassifierAdapter
    for name in ("detection_frame", "observation_payloads", "tracked_payload"):
        assert getattr(pipeline, name) is getattr(tracker_adapter, name)


def _msgpack_calls(path: Path) -> list[str]:
    tree = ast.parse(path.read_text(encoding="utf-8"))
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id == "msgpack":
            out.append(f"{path.relative_to(ROOT)}:{node.lineno} msgpack.{node.attr}")
    return out


def test_no_service_or_evaluator_code_packs_or_unpacks_messages_itself() -> None:
    """msgpack is used directly only by the schemas (and by the load generators of the benchmarks, which build
    their frames once from a validated model)."""
    areas = [ROOT / "services", ROOT / "eval", ROOT / "runtime", ROOT / "stack"]
    found = [hit for area in areas for path in sorted(area.rglob("*.py")) for hit in _msgpack_calls(path)]
    assert found == []
