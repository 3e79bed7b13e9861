"""`BackendRegistry`: a role's backends by name, each imported only when it is built.

Every hardware role (the arm, the force sensor, the master device, the camera) names its
backends in its package's `backends.py` as `"module:Class"` strings, so choosing the
simulation never imports pyserial, hidapi, websockets or OpenCV. A name the registry does not
hold is a `ConfigError` naming the configuration key that chose it.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Mapping
from typing import Any, Generic, TypeVar, cast

from services.bus.bounds import short
from services.bus.errors import ConfigError

R = TypeVar("R")


class BackendRegistry(Generic[R]):
    """Backend name → `"module:Class"` (any callable returning an `R`) for one role.

    `key` is the configuration key that chooses the backend (e.g. "arm.driver"); `what` names
    the role in errors ("arm").
    """

    def __init__(self, key: str, what: str, entries: Mapping[str, str]) -> None:
        for name, target in entries.items():
            module, _, attr = target.partition(":")
            if not module or not attr:
                raise ValueError(f"backend {name!r}: {target!r} is not 'module:Class'")
        self.key = key
        self.what = what
        self._entries = dict(entries)

    @property
    def names(self) -> tuple[str, ...]:
        """The backend names, in declaration order."""
        return tuple(self._entries)

    def load(self, name: str) -> Callable[..., R]:
        """The constructor of backend `name`, its module imported now (ConfigError if none)."""
        target = self._entries.get(name)
        if target is None:
            raise ConfigError(
                self.key,
                f"unknown {self.what} {short(repr(name))}, expected one of {', '.join(self.names)}",
            )
        module, _, attr = target.partition(":")
        return cast(Callable[..., R], getattr(importlib.import_module(module), attr))

    def build(self, name: str, options: Mapping[str, Any]) -> R:
        """Backend `name` constructed with the keyword arguments `options`."""
        return self.load(name)(**options)
