"""Configuration, the Autoware way, one loader for every service.

Beside this module, per service, ``<service>.param.yaml`` holds the defaults in Autoware's layout
(``/**: ros__parameters: {...}``), a preset is ``<service>.<preset>.param.yaml`` (the classifier's ``paper`` and
``authors``, the detector's ``lite`` and ``paper``), and ``schema/<service>.schema.json`` is the JSON schema of the
pydantic model that validates it. The models are the source: ``python -m jitterguard.config.generate`` writes the
defaults files and the schemas from them, and a test fails when a checked-in file no longer matches its model.

:func:`load` layers, each over the last: the model's defaults, a preset, the user's ``--config`` file (flat, or
in Autoware's ``ros__parameters`` form), then command-line overrides. Unknown keys are errors, not silently kept:
a misspelt gate that quietly keeps its default is the kind of bug that costs a day on the vehicle.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any, TypeVar

import yaml
from pydantic import BaseModel, ValidationError

M = TypeVar("M", bound=BaseModel)
CONFIG_DIR = Path(__file__).resolve().parent


class ConfigError(ValueError):
    """A configuration that cannot be used; the message names the file and the key."""


def param_file(service: str, preset: str | None = None) -> Path:
    """Where the package keeps ``service``'s defaults (or one of its presets)."""
    return CONFIG_DIR / (f"{service}.{preset}.param.yaml" if preset else f"{service}.param.yaml")


def schema_file(name: str) -> Path:
    """Where the package keeps the JSON schema ``name`` (a service, or ``detector.architecture``)."""
    return CONFIG_DIR / "schema" / f"{name}.schema.json"


def presets(service: str) -> list[str]:
    """The names of ``service``'s shipped presets."""
    return sorted(p.name[len(service) + 1: -len(".param.yaml")] for p in CONFIG_DIR.glob(f"{service}.*.param.yaml"))


class _StrictLoader(yaml.SafeLoader):
    """YAML as a parameter file means it: a key given twice is an error (the loader kept the last, so a misspelt
    second entry silently won), so is a key that is a list or a mapping, and scalars resolve as YAML 1.2 reads
    them — ``1e-4`` is a number (YAML 1.1 needs ``1.0e-4``: the docs' own ``variance_floor: 1e-4`` had been
    refused as a string) and only ``true``/``false`` are booleans (``calibration: off`` had become ``False``)."""

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict[Any, Any]:
        seen: set[Any] = set()
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=deep)
            if not isinstance(key, (str, int, float, bool)) and key is not None:  # `? [a, b]`, `? {a: 1}`: their
                # TypeError (unhashable) out of `key in seen` had ended every --config in a traceback
                raise ConfigError(f"a key must be a name, got a {type(key).__name__}"
                                  f" (line {key_node.start_mark.line + 1})")
            if key in seen:
                raise ConfigError(f"key {key!r} given twice (line {key_node.start_mark.line + 1})")
            seen.add(key)
        return super().construct_mapping(node, deep=deep)


_StrictLoader.yaml_implicit_resolvers = {
    first: [(tag, rx) for tag, rx in resolvers if tag != "tag:yaml.org,2002:bool"]
    for first, resolvers in yaml.SafeLoader.yaml_implicit_resolvers.items()}
_StrictLoader.add_implicit_resolver("tag:yaml.org,2002:bool", re.compile(r"^(?:true|True|TRUE|false|False|FALSE)$"),
                                    list("tTfF"))
_StrictLoader.add_implicit_resolver("tag:yaml.org,2002:float",
                                    re.compile(r"^[-+]?(?:[0-9][0-9_]*(?:\.[0-9_]*)?|\.[0-9_]+)[eE][-+]?[0-9]+$"),
                                    list("-+0123456789."))


def read_params(path: str | Path) -> dict[str, Any]:
    """A parameter file's mapping: flat, or unwrapped from Autoware's ``<node or /**>: ros__parameters:``."""
    if not str(path).strip():  # Path("") is the current folder: "<flag>: : not a file" had named nothing
        raise ConfigError("empty path; give a file")
    p = Path(path)
    if not p.is_file():
        raise ConfigError(f"config file not found: {path}" if not p.exists() else f"{path}: not a file")
    try:
        doc = yaml.load(p.read_text(encoding="utf-8"), Loader=_StrictLoader)  # noqa: S506 - a SafeLoader
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{path}: cannot read ({type(exc).__name__})") from None
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: not valid YAML ({type(exc).__name__})") from None
    except RecursionError:  # a value nested thousands deep: the parser's own recursion
        raise ConfigError(f"{path}: nested too deeply to read") from None
    except (ValueError, OverflowError) as exc:  # a scalar YAML resolves but Python cannot hold: had been a traceback
        # (an integer of over 4300 digits, a date such as 2024-02-30, an explicit tag like !!int 1.5)
        raise ConfigError(f"{path}: a value cannot be read ({str(exc).splitlines()[0][:120]})") from None
    if doc is None:
        return {}
    if not isinstance(doc, dict):
        raise ConfigError(f"{path}: expected a mapping at the top level, got {type(doc).__name__}")
    if len(doc) == 1:
        (only,) = doc.values()
        if isinstance(only, dict) and isinstance(only.get("ros__parameters"), dict):
            return dict(only["ros__parameters"])
    if isinstance(doc.get("ros__parameters"), dict):
        return dict(doc["ros__parameters"])
    return doc


def preset_values(service: str, name: str) -> dict[str, Any]:
    """The keys a shipped preset sets (ConfigError naming the flag and the choices if there is no such preset)."""
    if name not in presets(service):
        raise ConfigError(f"--preset: unknown {service} preset {name!r}; expected one of {', '.join(presets(service))}")
    return read_params(param_file(service, name))


def load(model: type[M], path: str | Path | None = None, *, service: str | None = None, preset: str | None = None,
         overrides: dict[str, Any] | None = None, base: dict[str, Any] | None = None,
         flags: dict[str, str] | None = None) -> M:
    """``model`` from its defaults (or ``base``), then ``service``'s ``preset``, the file at ``path`` and the
    ``overrides`` that are not None (command-line flags: ``flags`` names each key's flag, ``--key-name`` if not);
    ConfigError names the flag, or the file and the field, that fails."""
    values: dict[str, Any] = dict(base or {})
    maps = _map_defaults(model)
    origin = ""  # defaults and flags only: a rule across fields is told as it is
    if preset is not None:
        _merge(values, preset_values(service or "", preset), maps)
        origin = f"preset {preset}"
    if path is not None:
        _merge(values, read_params(path), maps)
        origin = str(path)
    given = {k: v for k, v in (overrides or {}).items() if v is not None}
    _merge(values, given, maps)
    try:
        return model.model_validate(values)
    except ValidationError as exc:
        err = exc.errors(include_url=False)[0]
        loc = err.get("loc", ())
        msg = str(err.get("msg", "invalid")).removeprefix("Value error, ")  # pydantic's prefix to a rule's own words
        if loc and loc[0] in given:  # a flag's value: name the flag
            flag = (flags or {}).get(str(loc[0]), "--" + str(loc[0]).replace("_", "-"))
            raise ConfigError(f"{flag}: {msg}") from None
        # a rule across fields has no loc; pydantic's own steps (constrained-float, function-after[…]) are no field
        where = [w for w in (origin, ".".join(str(p) for p in loc if not _SCHEMA_STEP.match(str(p)))) if w]
        raise ConfigError(": ".join([*where, msg])) from None


_SCHEMA_STEP = re.compile(r"^(constrained-\w+|[\w-]+\[.*\])$")
"""A ``loc`` element that names a step of pydantic's validator (``constrained-float`` of an optional bounded float,
``function-after[…]``), not a field: it had been shown as part of the key (``sensor_height_m.constrained-float``)."""


def _map_defaults(model: type[BaseModel]) -> dict[str, dict[str, Any]]:
    """The model's fields whose values are maps (the classifier's per-class maps), with their defaults."""
    out = {}
    for name, field in model.model_fields.items():
        default = field.get_default(call_default_factory=True)
        if isinstance(default, dict):
            out[name] = default
    return out


def _merge(into: dict[str, Any], new: dict[str, Any], maps: dict[str, dict[str, Any]] | None = None) -> None:
    """Nested mappings are merged key by key (a file may tune one limit), everything else replaced. A map field
    (``maps``: each with its default) given entries takes them over what the layers below it say — the model's
    default when none does: a file holding ``alpha_per_class: {pedestrian: 1.5}`` had replaced the default map
    without a preset, every vehicle falling from 2.58 to ``alpha_default``, and merged into it with one —; given
    ``{}`` it is cleared (the paper preset's "no per-class values"; under a preset ``{}`` had been ignored)."""
    for k, v in new.items():
        if maps is not None and k in maps and isinstance(v, dict):
            below = into.get(k, maps[k])
            into[k] = {**below, **v} if v and isinstance(below, dict) else v
        elif isinstance(v, dict) and isinstance(into.get(k), dict):
            into[k] = dict(into[k])
            _merge(into[k], v)
        else:
            into[k] = v


def dump_params(config: BaseModel, title: str, rows: dict[str, int] | None = None, exclude: set[str] = frozenset()
                ) -> str:
    """``config`` as a parameter file in Autoware's layout, each field's description as its comment; lists named
    in ``rows`` are written ``rows[name]`` values a line (the tracker's 8x8 matrices)."""
    lines = [f"# {line}" if line else "#" for line in title.splitlines()]
    lines += ["/**:", "  ros__parameters:"]
    values = config.model_dump(mode="json", exclude=set(exclude))
    for name, value in values.items():
        field = type(config).model_fields[name]
        if field.description:
            lines += [f"    # {line}" for line in _wrap(field.description, 110)]
        if rows and name in rows and isinstance(value, list):
            n = rows[name]
            chunks = [", ".join(repr(v) for v in value[i:i + n]) for i in range(0, len(value), n)]
            lines.append(f"    {name}:")
            lines += [f"      {'[' if i == 0 else ' '}{c}{']' if i == len(chunks) - 1 else ','}" for i, c in enumerate(chunks)]
        elif isinstance(value, dict) and value:
            text = yaml.safe_dump({name: value}, sort_keys=False, default_flow_style=False, width=110).rstrip()
            lines += [f"    {line}" for line in text.splitlines()]
        else:
            text = yaml.safe_dump(value, default_flow_style=True, width=10**6).replace("\n...", "").strip()
            lines.append(f"    {name}: {text}")
    return "\n".join(lines) + "\n"


def _wrap(text: str, width: int) -> list[str]:
    out, line = [], ""
    for word in text.split():
        if line and len(line) + 1 + len(word) > width:
            out.append(line)
            line = word
        else:
            line = f"{line} {word}" if line else word
    return out + ([line] if line else [])
