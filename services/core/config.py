"""Configuration: frozen pydantic models, loaded with one precedence rule.

defaults (the model) < a base layer (the trainer's preset) < YAML file < environment
(VIEWSCALE_SECTION__FIELD=value) < CLI overrides (``--set section.field=value``). Values from env
and CLI are parsed as YAML scalars/flow values, so ``--set bus.connect=[tcp/127.0.0.1:7447]`` and
``VIEWSCALE_CONTROL_HZ=20`` both work.
"""

from __future__ import annotations

import difflib
import os
import types
import typing
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import Annotated, Any, TypeVar, Union

import yaml
from pydantic import AfterValidator, BaseModel, ConfigDict, Tag, ValidationError

ENV_PREFIX = "VIEWSCALE_"

M = TypeVar("M", bound=BaseModel)


class Frozen(BaseModel):
    """Base for every config model: immutable, unknown keys are an error (catches typos)."""

    model_config = ConfigDict(frozen=True, extra="forbid")


class ConfigError(ValueError):
    """A configuration could not be loaded; the message names the source and the field."""


LOG_LEVELS = ("DEBUG", "INFO", "WARNING", "ERROR", "CRITICAL")


def named_twice(names: Iterable[str]) -> list[str]:
    """The names given more than once, sorted (a view list's typo: ``F,FL,F``)."""
    names = list(names)
    return sorted({n for n in names if names.count(n) > 1})


def checked_names(names: list[str] | None, if_empty: str) -> list[str] | None:
    """A config's list of camera names: None (its default), or at least one name, each given once;
    ValueError otherwise (``if_empty``: the message for an empty list, saying what leaving it out gives)."""
    if names is not None:
        if not names:
            raise ValueError(if_empty)
        if twice := named_twice(names):
            raise ValueError(f"names {', '.join(twice)} more than once")
    return names


def log_level_name(value: str) -> str:
    """``"info"`` -> ``"INFO"``; a name that is not a logging level is an error (not INFO in silence)."""
    name = str(value).strip().upper()
    if name not in LOG_LEVELS:
        raise ValueError(f"{value!r} is not a logging level; one of {', '.join(LOG_LEVELS)} (any case)")
    return name


LogLevel = Annotated[str, AfterValidator(log_level_name)]


def deep_merge(base: dict[str, Any], top: Mapping[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for key, value in top.items():
        if isinstance(value, Mapping) and isinstance(out.get(key), Mapping):
            out[key] = deep_merge(dict(out[key]), value)
        else:
            out[key] = value
    return out


def _nest(path: list[str], value: Any) -> dict[str, Any]:
    node: Any = value
    for part in reversed(path):
        node = {part: node}
    return node


def _parse_value(text: str) -> Any:
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError:
        return text


def parse_overrides(items: Iterable[str]) -> dict[str, Any]:
    """``["a.b=1", "c=[x, y]"]`` -> ``{"a": {"b": 1}, "c": ["x", "y"]}``."""
    merged: dict[str, Any] = {}
    for item in items:
        if "=" not in item:
            raise ConfigError(f"override {item!r} must look like key.path=value")
        key, _, raw = item.partition("=")
        path = [p for p in key.strip().split(".") if p]
        if not path:
            raise ConfigError(f"override {item!r} has an empty key")
        merged = deep_merge(merged, _nest(path, _parse_value(raw)))
    return merged


def env_overrides(environ: Mapping[str, str], prefix: str = ENV_PREFIX) -> dict[str, Any]:
    merged: dict[str, Any] = {}
    for name, raw in environ.items():
        if not name.startswith(prefix) or name == prefix + "CONFIG":
            continue
        path = [p.lower() for p in name[len(prefix) :].split("__") if p]
        if path:
            merged = deep_merge(merged, _nest(path, _parse_value(raw)))
    return merged


# The top-level keys of the services' shared YAML file (deploy/sim.yaml, deploy/real.yaml): one
# section per service, and the keys every section shares. A key starting with ``x-`` is the user's
# own (YAML anchors, as in compose files).
SECTIONS = ("sim", "camera", "robot", "teleop", "recorder", "session", "policy", "worker", "trainer")
SHARED_KEYS = ("bus", "world")


def read_yaml(path: str | Path) -> dict[str, Any]:
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"config file {path} does not exist")
    return yaml_mapping(path.read_text(), f"config file {path}")


def yaml_mapping(text: str, what: str) -> dict[str, Any]:
    """The mapping YAML ``text`` holds; a ConfigError naming ``what`` (a file) otherwise."""
    try:
        data = yaml.safe_load(text) or {}
    except yaml.YAMLError as exc:
        raise ConfigError(f"{what} is not valid YAML: {exc}") from exc
    if not isinstance(data, dict):
        raise ConfigError(f"{what} must hold a mapping at the top level")
    return data


def validate_config(
    model: type[M],
    data: Mapping[str, Any],
    base: Callable[[Mapping[str, Any]], dict[str, Any]] | None = None,
    source: str = "",
) -> M:
    """Validate ``data`` as ``model``, over the base layer ``base(data)`` when given (a preset named
    by the data itself); a ConfigError names the source and the field."""
    if base is not None:
        data = deep_merge(base(data), data)
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(f"invalid {model.__name__} config{source}: {describe_errors(exc, model)}") from exc


def setting_paths(model: type[BaseModel], prefix: str = "") -> list[str]:
    """Every setting of ``model`` as a dotted path, nested models' settings included."""
    paths = []
    for name, field in model.model_fields.items():
        kind = field.annotation
        if isinstance(kind, type) and issubclass(kind, BaseModel):
            paths += setting_paths(kind, f"{prefix}{name}.")
        else:
            paths.append(f"{prefix}{name}")
    return paths


def _tagged_members(kind: Any) -> dict[str, Any]:
    """A discriminated union's members by their tag (a driver field: ``{"sim": SimRobotConfig, ...}``)."""
    members = {}
    if typing.get_origin(kind) in (Union, types.UnionType):
        for arg in typing.get_args(kind):
            if typing.get_origin(arg) is Annotated:
                inner, *meta = typing.get_args(arg)
                members.update({m.tag: inner for m in meta if isinstance(m, Tag)})
    return members


def _is_model(kind: Any) -> bool:
    return isinstance(kind, type) and issubclass(kind, BaseModel)


def _written_path(model: type[BaseModel], loc: tuple[Any, ...]) -> tuple[str, type[BaseModel] | None]:
    """pydantic's ``loc`` as the user wrote it (``driver.ur.hots`` -> ``driver.hots``: the tags of
    driver unions are pydantic's, not the user's), and the model whose field its last part would be."""
    written: list[str] = []
    kind: Any = model
    owner: type[BaseModel] | None = None
    parts = list(loc)
    i = 0
    while i < len(parts):
        part = parts[i]
        written.append(str(part))
        owner = kind if _is_model(kind) else None
        if owner is not None:
            field = owner.model_fields.get(str(part))
            kind = field.annotation if field is not None else None
        elif typing.get_origin(kind) in (list, tuple, dict):  # an item, by index or key
            kind = typing.get_args(kind)[-1] if typing.get_args(kind) else None
        else:
            kind = None
        members = _tagged_members(kind)
        if members and i + 1 < len(parts) and parts[i + 1] in members:
            kind = members[parts[i + 1]]
            i += 1  # the tag
        elif typing.get_origin(kind) in (Union, types.UnionType):  # ``X | None``
            models = [a for a in typing.get_args(kind) if _is_model(a)]
            kind = models[0] if len(models) == 1 else kind
        i += 1
    return ".".join(written), owner


def _unknown_setting(loc: str, model: type[BaseModel] | None, owner: type[BaseModel] | None = None) -> str:
    """``no such setting``, with the settings it may have meant: the same name elsewhere (``lr`` for
    ``optim.lr``), or a close spelling; ``owner``: the model the setting was given to (a driver's
    config, which ``model``'s own settings do not list)."""
    if model is None:
        return "no such setting"
    known = setting_paths(model)
    parent = loc.rsplit(".", 1)[0] if "." in loc else ""
    if owner is not None and owner is not model:  # (its own settings first: the nearest meant)
        known = [*setting_paths(owner, f"{parent}."), *(p for p in known if not p.startswith(f"{parent}."))]
    leaf = loc.rsplit(".", 1)[-1]
    near = [p for p in known if p.rsplit(".", 1)[-1] == leaf]
    if not near:
        alike = set(difflib.get_close_matches(leaf, [p.rsplit(".", 1)[-1] for p in known], n=3, cutoff=0.75))
        near = [p for p in known if p.rsplit(".", 1)[-1] in alike]
    if near:
        return f"no such setting (did you mean {' or '.join(near[:3])}?)"
    siblings = [p.rsplit(".", 1)[-1] for p in known if p.startswith(f"{parent}.") and p.count(".") == loc.count(".")]
    if parent and 0 < len(siblings) <= 12:  # (a section's own settings, when they are few enough to read)
        return f"no such setting ({parent} has {', '.join(siblings)})"
    return "no such setting"


def describe_errors(exc: ValidationError, model: type[BaseModel] | None = None) -> str:
    """pydantic's errors on one line: ``field.path: message (got value)``, joined by ``; ``. With
    ``model``, paths are the ones the user wrote (no driver tags), and an unknown setting names
    the settings it may have meant (before: pydantic's 'Extra inputs are not permitted')."""
    parts = []
    for e in exc.errors():
        if model is not None:
            loc, owner = _written_path(model, e["loc"])
        else:
            loc, owner = ".".join(str(p) for p in e["loc"]), None
        got = e.get("input")
        shown = "" if isinstance(got, dict) or got is None else f" (got {str(got)[:60]!r})"
        # our validators' own words, without pydantic's 'Value error, ' before them
        msg = str(e["ctx"]["error"]) if e["type"] == "value_error" and "error" in e.get("ctx", {}) else e["msg"]
        if e["type"] == "extra_forbidden":
            msg = _unknown_setting(loc, model, owner)
        parts.append(f"{loc}: {msg}{shown}" if loc else f"{msg}{shown}")  # (no loc: a check across fields)
    return "; ".join(parts)


def load_config(
    model: type[M],
    yaml_path: str | Path | None = None,
    overrides: Iterable[str] = (),
    environ: Mapping[str, str] | None = None,
    section: str | None = None,
    base: Callable[[Mapping[str, Any]], dict[str, Any]] | None = None,
    yaml_from_env: bool = True,
) -> M:
    """Build ``model`` from defaults < base < YAML < env < CLI overrides.

    ``section`` picks one top-level key of a shared YAML file (deploy/sim.yaml holds every
    service's section, plus shared top-level keys such as ``bus`` that any model with that field
    takes); env and CLI overrides are relative to that section. Environment keys
    only apply to fields the model has, so one environment can carry several services' settings.
    ``base``: see ``validate_config``. ``yaml_from_env``: without ``yaml_path``, read the file
    ``VIEWSCALE_CONFIG`` names (the services' shared file; the trainer's settings are not in it).
    """
    environ = os.environ if environ is None else environ
    data: dict[str, Any] = {}
    if yaml_path is None and yaml_from_env:
        yaml_path = environ.get(ENV_PREFIX + "CONFIG")
    if yaml_path:
        raw = read_yaml(yaml_path)
        if section is not None:
            known = {*SECTIONS, *SHARED_KEYS, section, *model.model_fields}
            unknown = [k for k in raw if k not in known and not str(k).startswith("x-")]
            if unknown:  # (a misspelt section was ignored: its settings never took effect)
                raise ConfigError(
                    f"config file {yaml_path}: {str(unknown[0])!r} is no service's section "
                    f"(sections: {', '.join(SECTIONS)}; shared: {', '.join(SHARED_KEYS)}; x-... for your own keys)"
                )
            body = raw.get(section, {}) or {}
            if not isinstance(body, dict):
                raise ConfigError(f"section {section!r} of {yaml_path} must be a mapping")
            # Top-level keys the model also has (``bus``) are shared by every service's section.
            shared = {k: v for k, v in raw.items() if k in model.model_fields and k != section}
            raw = deep_merge(shared, body)
        data = deep_merge(data, raw)
    env = env_overrides(environ)
    env = {k: v for k, v in env.items() if k in model.model_fields}
    data = deep_merge(data, env)
    overrides = list(overrides)
    if section is not None and section not in model.model_fields:
        named = [o for o in overrides if o.strip().startswith(f"{section}.")]
        if named:  # (before: "robot: no such setting", for the section name a YAML file starts with)
            raise ConfigError(
                f"--set {named[0]}: a setting here is named inside the {section!r} section, without "
                f"'{section}.' before it: --set {named[0].strip()[len(section) + 1 :]}"
            )
    data = deep_merge(data, parse_overrides(overrides))
    return validate_config(model, data, base, f" (from {yaml_path})" if yaml_path else "")
