"""Write the shipped defaults files and JSON schemas from the pydantic models (``python -m
jitterguard.config.generate``; ``--check`` only says which files differ, exit 1). Run it after changing a config
model; ``tests/config/test_config_files.py`` fails until the checked-in files match again."""

from __future__ import annotations

import json
import sys
from collections.abc import Callable
from pathlib import Path

from pydantic import BaseModel

from ..services.classifier.config import ClassifierParams
from ..services.detector.config import DetectorConfig, DetectorParams
from ..services.tracker.config import default_config, dump_config
from . import dump_params, param_file, schema_file


def _tracker() -> tuple[BaseModel, str]:
    return default_config(), dump_config(default_config())


def _classifier() -> tuple[BaseModel, str]:
    p = ClassifierParams()
    return p, dump_params(p, "jitterguard classifier (jitterguard classifier --config FILE); presets:"
                          " classifier.<name>.param.yaml", exclude={"schema_version"})


def _detector() -> tuple[BaseModel, str]:
    p = DetectorParams()
    return p, dump_params(p, "jitterguard detector (jitterguard detector --config FILE); architectures:"
                          " detector.<preset>.param.yaml")


DEFAULTS: dict[str, Callable[[], tuple[BaseModel, str]]] = {
    "tracker": _tracker, "classifier": _classifier, "detector": _detector}


def expected_files() -> dict[Path, str]:
    """Every generated file and the text it must hold."""
    out: dict[Path, str] = {}
    for service, make in DEFAULTS.items():
        model, text = make()
        out[param_file(service)] = text
        out[schema_file(service)] = _schema(type(model))
    out[schema_file("detector.architecture")] = _schema(DetectorConfig)
    return out


def _schema(model: type[BaseModel]) -> str:
    return json.dumps(model.model_json_schema(), indent=2, sort_keys=True) + "\n"


def main(argv: list[str] | None = None) -> int:
    check = "--check" in (argv if argv is not None else sys.argv[1:])
    stale = []
    for path, text in expected_files().items():
        if not path.is_file() or path.read_text(encoding="utf-8") != text:
            stale.append(path)
            if not check:
                path.parent.mkdir(parents=True, exist_ok=True)
                path.write_text(text, encoding="utf-8")
    for path in stale:
        print(f"{'differs' if check else 'wrote'}: {path}")
    return 1 if check and stale else 0


if __name__ == "__main__":
    raise SystemExit(main())
