"""Drivers by name: how a config picks the implementation of a camera, robot or teleop.

A *driver* is whatever sits behind one of those interfaces: real hardware, the MuJoCo sim, the
scripted expert, a policy client. Each interface keeps one ``Registry`` of its drivers: a name,
the implementing class as ``"package.module:Class"`` (imported only when it is built, so a
process loads only the driver it runs), and a typed config model whose ``type`` field is that
name. A service config holds the driver's config in a field typed ``registry.config_type()``,
a pydantic union discriminated by ``type``::

    robot:
      driver: {type: sim, task: lift}              # a registered name, with its typed fields
      driver: {type: mylab.arms:MyArm, ip: 10.0.0.2}   # a lab's own class

A lab's own class (``type: package.module:Class``) subclasses the interface and may declare a
nested ``Config`` (a frozen pydantic model); the other keys of its entry are validated against
it when the driver is built, and an unknown key is an error either way.
"""

from __future__ import annotations

import importlib
import re
from dataclasses import dataclass
from typing import Annotated, Any, ClassVar, Generic, Literal, TypeVar, Union

from pydantic import ConfigDict, Discriminator, Field, Tag, ValidationError, field_validator

from services.core.config import ConfigError, Frozen

T = TypeVar("T")
_CLASS_PATH = re.compile(r"^[A-Za-z_][\w.]*:[A-Za-z_]\w*$")
EXTERNAL = "external"  # the discriminator tag of `type: package.module:Class` entries


World = Literal["sim", "real"]  # the shared top-level `world` key of deploy/sim.yaml and deploy/real.yaml


class DriverConfig(Frozen):
    """Base of every registered driver's config: ``type`` names the driver."""

    sim_only: ClassVar[bool] = False  # needs the simulator (its task state or its world)
    type: str  # the registered name (a Literal in each subclass)


def check_world(driver: Any, world: World, concept: str) -> None:
    """Refuse a sim-only driver in a real-world session, at start-up rather than tick by tick."""
    if world == "real" and getattr(driver, "sim_only", False):
        why = " ".join((type(driver).__doc__ or "").split())
        raise ValueError(
            f"{concept} driver {driver.type!r} only works in sim (world: real): {why} "
            "Pick a driver for hardware, or world: sim"
        )


class ExternalDriverConfig(Frozen):
    """``type: package.module:Class`` plus that class's own settings (checked when it is built)."""

    model_config = ConfigDict(frozen=True, extra="allow")
    type: str = Field(pattern=_CLASS_PATH.pattern)  # the lab's class

    @property
    def settings(self) -> dict[str, Any]:
        return dict(self.model_extra or {})


@dataclass(frozen=True)
class Entry:
    name: str  # what configs write as `type`
    target: str  # "package.module:Class"
    config: type[DriverConfig]  # its typed settings


def import_class(path: str) -> type:
    """``"package.module:Class"`` -> the class; a ConfigError says what is missing."""
    if not _CLASS_PATH.match(path):
        raise ConfigError(f"{path!r} must look like 'package.module:ClassName'")
    module_name, _, class_name = path.partition(":")
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise ConfigError(f"module {module_name!r} cannot be imported: {exc}") from exc
    cls = getattr(module, class_name, None)
    if not isinstance(cls, type):
        raise ConfigError(f"{module_name} has no class {class_name!r}")
    return cls


class Registry(Generic[T]):
    """The drivers of one interface (``base``), by name."""

    def __init__(self, concept: str, base: type[T]):
        self.concept = concept  # "camera", "robot", "teleop": used in messages
        self.base = base
        self._entries: dict[str, Entry] = {}

    def register(self, name: str, target: str, config: type[DriverConfig]) -> None:
        if name in self._entries:
            raise ValueError(f"{self.concept} driver {name!r} is registered twice")
        if ":" in name or not _CLASS_PATH.match(target):
            raise ValueError(f"bad {self.concept} driver entry {name!r} -> {target!r}")
        if config.model_fields["type"].default != name:
            raise ValueError(f"{config.__name__}.type must default to {name!r}")
        self._entries[name] = Entry(name, target, config)

    @property
    def names(self) -> list[str]:
        return list(self._entries)

    def config_type(self) -> Any:
        """The pydantic type of a config field holding one of these drivers' configs."""
        names = self.names
        concept = self.concept

        def tag(value: Any) -> str:
            t = value.get("type") if isinstance(value, dict) else getattr(value, "type", None)
            return t if t in names else EXTERNAL

        class External(ExternalDriverConfig):
            @field_validator("type", mode="before")
            @classmethod
            def _known(cls, v: Any) -> Any:
                if not isinstance(v, str) or not _CLASS_PATH.match(v):
                    raise ValueError(
                        f"unknown {concept} driver {v!r}: choose one of {', '.join(names)} "
                        "or give your own class as package.module:ClassName"
                    )
                return v

        External.__name__ = External.__qualname__ = f"External{concept.title()}DriverConfig"
        members = [Annotated[e.config, Tag(e.name)] for e in self._entries.values()]
        members.append(Annotated[External, Tag(EXTERNAL)])
        return Annotated[Union[tuple(members)], Discriminator(tag)]  # noqa: UP007  (a union built at run time)

    def resolve(self, cfg: DriverConfig | ExternalDriverConfig) -> tuple[type[T], Any]:
        """The driver class for ``cfg`` and the typed config to build it with."""
        entry = self._entries.get(cfg.type)
        if entry is not None:
            cls = import_class(entry.target)
            typed: Any = cfg
        else:
            cls = import_class(cfg.type)
            settings = cfg.settings if isinstance(cfg, ExternalDriverConfig) else {}
            own = getattr(cls, "Config", None)
            if own is not None:
                try:
                    typed = own.model_validate(settings)
                except ValidationError as exc:
                    raise ConfigError(f"invalid settings for {self.concept} driver {cfg.type}:\n{exc}") from exc
            elif settings:
                raise ConfigError(
                    f"{self.concept} driver {cfg.type} declares no Config, so it takes no "
                    f"settings (got {', '.join(sorted(settings))})"
                )
            else:
                typed = None
        if not (isinstance(cls, type) and issubclass(cls, self.base)):
            raise ConfigError(f"{cfg.type} is not a {self.base.__name__} (the {self.concept} driver interface)")
        return cls, typed

    def build(self, cfg: DriverConfig | ExternalDriverConfig, **context: Any) -> T:
        """Import and construct the driver: ``Class.from_config(typed_config, **context)``."""
        cls, typed = self.resolve(cfg)
        return cls.from_config(typed, **context)  # type: ignore[attr-defined]
