"""Which services of a run are live, from their liveliness tokens (``ebrl/live/<run>/<role>/<instance>``)."""

from __future__ import annotations

import logging
from typing import Any, Callable

from ebrl.bus import keys

log = logging.getLogger(__name__)


class LivePeers:
    """The live tokens of one run (of one ``role``, if given). ``on_join(role, callback)`` runs ``callback()``
    on the event loop each time a service of ``role`` (re)appears. A service that leaves is logged as a
    warning while ``warn()`` is true (false once this process is stopping itself, say)."""

    def __init__(self, bus: Any, run: str, role: str | None = None, warn: Callable[[], bool] = lambda: True):
        self.keys: set[str] = set()
        self._joined: dict[str, list[Callable[[], None]]] = {}
        self._warn = warn
        bus.watch_liveliness(keys.live(run, role) if role else keys.live_all(run), self._on_change)

    def on_join(self, role: str, callback: Callable[[], None]) -> None:
        self._joined.setdefault(role, []).append(callback)

    def count(self, role: str) -> int:
        return sum(1 for k in self.keys if keys.role_of(k) == role)

    def has(self, role: str) -> bool:
        return any(keys.role_of(k) == role for k in self.keys)

    def _on_change(self, key: str, alive: bool) -> None:
        (self.keys.add if alive else self.keys.discard)(key)
        log.debug("%s %s", key, "live" if alive else "gone")
        if not alive and self._warn():
            log.warning("%s left the bus", key)
        if alive:
            for callback in self._joined.get(keys.role_of(key), ()):
                callback()
