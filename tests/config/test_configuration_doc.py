"""docs/configuration.md tells the truth about the services' settings: every key of every service's model is named
there, every key it names in a table is a real one, and every default it states as a value (a table's default
column, a "`key` (value" or "`key` (default value" in the prose) is the model's.

The models are the source (``jitterguard/config/__init__.py``): the shipped param.yaml files are generated from
them and ``test_config_files.py`` holds those to the models; this holds the page a reader tunes from to them too.
"""

from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Any

import pytest
import yaml
from pydantic import BaseModel

from jitterguard.config import _StrictLoader
from jitterguard.schemas.wire import Limits
from jitterguard.services.classifier.cli import ClassifierParams
from jitterguard.services.detector.config import DetectorParams
from jitterguard.services.tracker.config import TrackerConfig
from jitterguard.stream_order import StreamLimits

PAGE = Path(__file__).resolve().parents[2] / "docs" / "configuration.md"
MODELS: dict[str, type[BaseModel]] = {"classifier": ClassifierParams, "tracker": TrackerConfig,
                                      "detector": DetectorParams, "limits": Limits, "stream": StreamLimits}
NOT_SETTINGS = {"schema_version"}  # the wire's version stamp, not something to tune
UNSTATED = object()
"""A default cell or parenthesis that says it in words ("the shipped file", "Autoware's"): nothing to compare."""


def _section(text: str, title: str) -> str:
    """The text of the ``## title`` section, up to the next ``## ``."""
    start = text.index(f"\n## {title}")
    end = text.find("\n## ", start + 1)
    return text[start:] if end < 0 else text[start:end]


def stated_value(text: str) -> Any:
    """A default as the page states it, read as the parameter files are (YAML), or UNSTATED for words."""
    text = text.strip()
    if re.fullmatch(r"`[^`]*`", text):
        text = text[1:-1]
    elif "`" in text or re.search(r"[A-Za-z]{2,}", text) and text not in ("true", "false", "none", "null"):
        return UNSTATED
    if text == "none":
        return None
    try:
        return yaml.load(text, Loader=_StrictLoader)  # as the parameter files are read (YAML 1.2 scalars)
    except yaml.YAMLError:
        return UNSTATED


def agrees(stated: Any, default: Any) -> bool:
    """Whether a stated default is the model's (numbers compared as numbers, sequences item by item)."""
    if isinstance(default, BaseModel):
        default = default.model_dump()
    if isinstance(stated, bool) or isinstance(default, bool):
        return stated is default
    if isinstance(stated, (int, float)) and isinstance(default, (int, float)):
        return math.isclose(stated, default, rel_tol=1e-9)
    if isinstance(stated, list) and isinstance(default, (list, tuple)):
        return len(stated) == len(default) and all(agrees(s, d) for s, d in zip(stated, default))
    return stated == default


def table_rows(section: str) -> list[tuple[list[str], str]]:
    """Each row of the key tables in ``section``: the keys named in its first cell and its default cell."""
    rows = []
    for line in section.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")] if line.startswith("| `") else []
        if len(cells) >= 3:
            rows.append((re.findall(r"`([a-z_][a-z0-9_]*)`", cells[0]), cells[1]))
    return rows


def prose_defaults(text: str) -> list[tuple[str, str]]:
    """Each "`key` (value" / "`key` (default value" in ``text``'s prose: the key and the value as written."""
    pattern = r"`([a-z_][a-z0-9_]*)`\s*\((?:default\s+)?(`[^`]*`|[-+0-9.e]+(?=[:;,)]|\s+(?:s|m|MiB)\b))"
    prose = "\n".join(line for line in text.splitlines() if not line.startswith("|"))
    return re.findall(pattern, prose)


def _default(model: type[BaseModel], key: str) -> Any:
    field = model.model_fields[key]
    return field.get_default(call_default_factory=True)


def test_the_readers_read_defaults_as_written() -> None:
    assert stated_value("`z_test`") == "z_test" and stated_value("1e-4") == 1e-4 and stated_value("none") is None
    assert stated_value("`[20, 40]`") == [20, 40] and stated_value("`{}`") == {} and stated_value("true") is True
    assert stated_value("the authors' values") is UNSTATED and stated_value("2 for car, truck") is UNSTATED
    assert agrees(20, 20.0) and agrees([20, 40], (20.0, 40.0)) and not agrees(1, True) and not agrees(0.1, 0.2)
    assert prose_defaults("`max_objects` (1000), `confirm_s` (0.3 s on it) and `flips` (default `false`), not\n"
                          "`max_correlation` (1 + 10⁻⁶) nor\n| `window_size` | 20 | at `window_reference_hz` (2 s) |") == [
        ("max_objects", "1000"), ("confirm_s", "0.3"), ("flips", "`false`")]


@pytest.mark.parametrize("name", sorted(MODELS))
def test_every_key_of_every_service_is_named_on_the_page(name: str) -> None:
    page = PAGE.read_text(encoding="utf-8")
    missing = [k for k in MODELS[name].model_fields if k not in NOT_SETTINGS and f"`{k}`" not in page]
    assert missing == []


@pytest.mark.parametrize(("title", "model"), [("The classifier", ClassifierParams), ("The tracker", TrackerConfig)])
def test_every_table_row_is_a_key_with_the_models_default(title: str, model: type[BaseModel]) -> None:
    rows = table_rows(_section(PAGE.read_text(encoding="utf-8"), title))
    assert len(rows) >= 15, f"the {title} tables were not found"
    bad = []
    for keys, cell in rows:
        for key in keys:
            if key not in model.model_fields:
                bad.append(f"{key}: not a key of {model.__name__}")
                continue
            stated = stated_value(cell)
            if stated is not UNSTATED and not agrees(stated, _default(model, key)):
                bad.append(f"{key}: the page says {cell}, the model {_default(model, key)!r}")
    assert bad == []


def test_every_default_stated_in_the_prose_is_the_models() -> None:
    page = PAGE.read_text(encoding="utf-8")
    checked, bad = 0, []
    for title, models in (("The classifier", (ClassifierParams, Limits, StreamLimits)),
                          ("The tracker", (TrackerConfig, Limits, StreamLimits)), ("The detector", (DetectorParams,))):
        for key, text in prose_defaults(_section(page, title)):
            model = next((m for m in models if key in m.model_fields), None)
            stated = stated_value(text)
            if model is None or stated is UNSTATED or (isinstance(stated, str) and  # a file named beside the key
                                                        not isinstance(_default(model, key), str)):
                continue
            checked += 1
            if not agrees(stated, _default(model, key)):
                bad.append(f"{title}: {key}: the page says {text}, the model {_default(model, key)!r}")
    assert checked >= 15 and bad == []
