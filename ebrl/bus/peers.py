"""Which services of a run are live, from their liveliness tokens (``ebrl/live/<run>/<role>/<instance>``).

What rests on them (generation's batch, the iteration schedule: how many simulator hosts serve) counts only
the instances the run has (:func:`plan_admits`, from its launcher's plan: ``ebrl.hosts.sim_hosts``); a token of
any other instance is kept apart, counted (``unknown_seen``) and changes nothing. The launcher's router refuses
such tokens already where it enforces identities per instance (``ebrl.bus.auth``); this holds where it does not
(a mesh, ``bus.mode = "peer"``)."""

from __future__ import annotations

import logging
from typing import Any, Callable

from ebrl import graph, keys

log = logging.getLogger(__name__)


def plan_admits(sim_hosts: frozenset[int] | None) -> Callable[[str, str], bool]:
    """Whether instance ``(role, instance)`` is one the run has: a simulator of one of ``sim_hosts`` (None: of
    any host, by number), any instance of the other roles (their tokens move no schedule)."""
    def admits(role: str, instance: str) -> bool:
        if role != "sim":
            return True
        return instance.isdigit() and (sim_hosts is None or int(instance) in sim_hosts)
    return admits


class LivePeers:
    """The live tokens of one run (of one ``role``, if given). ``on_join(role, callback)`` runs ``callback()``
    on the event loop each time a service of ``role`` (re)appears. A service that leaves is logged as a
    warning while ``warn()`` is true (false once this process is stopping itself, say). ``admits(role,
    instance)``: whether the run has that instance (:func:`plan_admits`); a token of one it does not have is
    not counted, not announced, only counted in ``unknown_seen`` (and logged once)."""

    def __init__(self, bus: Any, run: str, role: str | None = None, warn: Callable[[], bool] = lambda: True,
                 admits: Callable[[str, str], bool] = lambda role, instance: True):
        self.keys: set[str] = set()  # live tokens of instances the run has
        self.unknown: set[str] = set()  # live tokens of instances it does not have
        self.unknown_seen = 0  # tokens of such instances that appeared, each time
        self._joined: dict[str, list[Callable[[], None]]] = {}
        self._warn, self._admits = warn, admits
        # the tokens of role's instances, or every token of the run (what a simulator watches)
        bus.watch_liveliness(graph.keys_of(run, role, "*").token() if role else graph.keys_of(run, "sim").watch(),
                             self._on_change)

    def on_join(self, role: str, callback: Callable[[], None]) -> None:
        self._joined.setdefault(role, []).append(callback)

    def count(self, role: str) -> int:
        return sum(1 for k in self.keys if keys.role_of(k) == role)

    def has(self, role: str) -> bool:
        return any(keys.role_of(k) == role for k in self.keys)

    def _known(self, key: str) -> bool:
        try:
            parsed = keys.parse(key)
        except ValueError:
            return False
        return self._admits(parsed.service, parsed.instance)

    def _on_change(self, key: str, alive: bool) -> None:
        if not self._known(key):
            if alive and key not in self.unknown:
                if not self.unknown_seen:
                    log.warning("liveliness token of an instance this run does not have: %s (not counted; "
                                "further ones only counted)", key)
                self.unknown_seen += 1
            (self.unknown.add if alive else self.unknown.discard)(key)
            return
        (self.keys.add if alive else self.keys.discard)(key)
        log.debug("%s %s", key, "live" if alive else "gone")
        if not alive and self._warn():
            log.warning("%s left the bus", key)
        if alive:
            for callback in self._joined.get(keys.role_of(key), ()):
                callback()
