"""One metric's record: its name, unit, publishers and meaning.

The catalog (:mod:`ebrl.metrics`) gathers the records: the stock services' from its modules, and any role's own from
its record in the service graph (``ebrl.graph.Role.metrics``), which is why this module sits below both and imports
neither."""

from __future__ import annotations

import re
from dataclasses import dataclass, field

# a placeholder of a family's name: ``<lane>`` in ``busy/<lane>``; it stands for a word without ``/`` or ``_``
# (a lane ``sim.g0``, a core ``3``, a stage ``train``), so that ``alloc/cores_<stage>`` is not also
# ``alloc/cores_per_env``
PLACEHOLDER = re.compile(r"<[a-z]+>")
PLACEHOLDER_VALUE = r"[A-Za-z0-9.]+"
RATE = "_per_s"  # a counter's rate over the last interval (ebrl.meter.Meter.metrics)


@dataclass(frozen=True)
class Metric:
    """A metric, or a family of them (``name`` with placeholders: ``train/staleness_hist_<k>``).

    ``unit``: what one unit is (``count``, ``s``, ``MiB``, ``fraction`` 0-1, ``version``, ``0/1``, ...).
    ``modules``: the files under ``ebrl/`` that publish it (the name, or the part after its namespace, is in
    their source: a test reads them). ``services``: the services whose reports carry it (by default the
    service its namespace names, which the catalog checks is a role's). ``counter``: counted with
    ``Service.count``, so every report carries the total ``name`` and ``name_per_s``, the rate over the interval
    since the previous report."""

    name: str
    unit: str
    meaning: str
    modules: tuple[str, ...]
    services: tuple[str, ...] = ()
    counter: bool = False
    pattern: re.Pattern = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if isinstance(self.modules, str):
            object.__setattr__(self, "modules", (self.modules,))
        if isinstance(self.services, str):
            object.__setattr__(self, "services", (self.services,))
        if not self.services:
            object.__setattr__(self, "services", (self.namespace,))
        pieces = [re.escape(p) for p in PLACEHOLDER.split(self.name)]
        rate = f"(?:{RATE})?" if self.counter else ""
        object.__setattr__(self, "pattern", re.compile(PLACEHOLDER_VALUE.join(pieces) + rate))

    @property
    def namespace(self) -> str:
        """What its name starts with: ``sim`` for ``sim/env_steps``."""
        return self.name.split("/", 1)[0]

    @property
    def family(self) -> bool:
        """True for a family of names (placeholders in ``name``)."""
        return PLACEHOLDER.search(self.name) is not None

    @property
    def pieces(self) -> list[str]:
        """The literal parts of ``name`` between its placeholders (the name itself for one metric)."""
        return [p for p in PLACEHOLDER.split(self.name) if p]

    def matches(self, name: str) -> bool:
        """Whether ``name`` (as published) is this metric: the name, a member of the family, or a counter's rate."""
        return self.pattern.fullmatch(name) is not None

    def names(self) -> tuple[str, ...]:
        """What a report carries under this record: ``name``, and ``name_per_s`` for a counter."""
        return (self.name, self.name + RATE) if self.counter else (self.name,)
