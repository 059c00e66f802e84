"""Config errors, field docs and the Section base every section of a config file derives from."""

from __future__ import annotations

import dataclasses
from dataclasses import field
from typing import Any, ClassVar

from ebrl import devices


class ConfigError(ValueError):
    """A config that cannot be used; the message names the field."""


def doc(text: str, default: Any = dataclasses.MISSING, factory: Any = dataclasses.MISSING) -> Any:
    if factory is not dataclasses.MISSING:
        return field(default_factory=factory, metadata={"doc": text})
    return field(default=default, metadata={"doc": text})


class Section:
    """A ``[section]`` of the config. Its types are checked as it is read; :meth:`check` then checks what its
    values mean, each section its own rules (:attr:`POSITIVE` fields and :meth:`_check`); the few rules that
    tie sections together are :func:`ebrl.config.schema.check_across`."""

    NAME: ClassVar[str] = ""
    POSITIVE: ClassVar[tuple[str, ...]] = ()  # fields that must be > 0

    def check(self) -> None:
        for key in self.POSITIVE:
            value = getattr(self, key)
            if not value > 0:  # NaN too
                raise ConfigError(f"{self.NAME}.{key} = {value}: must be > 0")
        self._check()

    def _check(self) -> None:
        """The section's rules beyond its positive fields."""


def _device(text: str, path: str) -> None:
    try:
        devices.check_syntax(text, path)
    except ValueError as exc:
        raise ConfigError(str(exc)) from None


def parse_slowdown(text: str) -> tuple[str, float, float]:
    """``"train=1.3@30"`` -> ``("train", 1.3, 30.0)``."""
    service, eq, rest = text.partition("=")
    factor, at, after = rest.partition("@")
    if not (eq and at and service):
        raise ValueError('expected "<service>=<factor>@<seconds>", e.g. "train=1.3@30"')
    value, seconds = float(factor), float(after)
    if value < 1 or seconds < 0:
        raise ValueError("the factor must be >= 1 and the seconds >= 0")
    return service.strip(), value, seconds
