"""The catalog of every metric a run publishes in its stats reports: one place where each is declared.

Each :class:`~ebrl.metric.Metric` names a metric (or a family, ``busy/<lane>``), its unit, the services
that report it, what it means and the modules that publish it. The stock services' records are in this package's
modules; a role may declare its own in its record of the service graph (``ebrl.graph.Role.metrics``), which is
where a new service declares them. ``docs/stats.md``'s table is generated from the catalog (``python
docs/gen.py``), a section per role (its ``Role.about``); tests check that every record's name is in the source of
the modules it names and that every metric real runs publish is here (``tests/test_metrics.py``), and
:func:`describe` looks a published name up::

    >>> describe("sim/env_steps_per_s").meaning
    'environment steps'

Data only: importing it imports neither torch nor zenoh.
"""

from __future__ import annotations

from typing import Iterable

from ebrl import graph
from ebrl.metric import Metric
from ebrl.metrics import alloc, common, evaluation, gen, launcher, observers, replay, sim, train

__all__ = ["CATALOG", "EVERY", "NAMESPACES", "SECTIONS", "Metric", "describe", "missing", "section_of"]

EVERY = common.EVERY  # the services that each report what every service reports (the launcher is not one)
NAMESPACES = tuple(role.stats for role in graph.ROLES.values() if role.stats)  # each role's own (ebrl.graph.Role)

CATALOG: tuple[Metric, ...] = (*sim.METRICS, *gen.METRICS, *train.METRICS, *replay.METRICS, *evaluation.METRICS,
                               *alloc.METRICS, *launcher.METRICS, *observers.METRICS,
                               *(m for role in graph.ROLES.values() for m in role.metrics), *common.METRICS)

# the page's sections, in order (each role's own metrics, then what every service reports), each with its line
SECTIONS = {**{role.stats: role.about for role in graph.ROLES.values() if role.stats},
            "every service": "What every service reports about itself (and, where it says so, the launcher)."}


def _check() -> None:
    for metric in CATALOG:
        if metric.services == (metric.namespace,) and metric.namespace not in NAMESPACES:
            raise ValueError(f"ebrl.metrics: {metric.name}: say which services publish it (services=...); no "
                             "role's own metrics are in its namespace (ebrl.graph.Role.stats)")
    for role in graph.ROLES.values():
        if role.stats and not role.about:
            raise ValueError(f"ebrl.graph: role {role.name!r} reports metrics of its own (stats=...): give it the "
                             "line of their section in docs/stats.md (about=...)")
        if stray := [m.name for m in role.metrics if m.namespace != role.stats]:
            raise ValueError(f"ebrl.graph: role {role.name!r} declares metrics outside its namespace "
                             f"{role.stats + '/' if role.stats else '(it has none: stats=...)'}: {', '.join(stray)}")


_check()

_BY_NAME = {m.name: m for m in CATALOG if not m.family}
_FAMILIES = [m for m in CATALOG if m.family]
if len(_BY_NAME) + len(_FAMILIES) != len(CATALOG):
    raise ValueError("ebrl.metrics: a name declared twice")


def describe(name: str) -> Metric | None:
    """The record of the metric ``name`` as a report carries it (``sim/env_steps_per_s``: the counter
    ``sim/env_steps``; ``busy/sim.g0``: the family ``busy/<lane>``), or None for a name the catalog lacks."""
    if (metric := _BY_NAME.get(name)) is not None:
        return metric
    if name.endswith("_per_s") and (metric := _BY_NAME.get(name[:-len("_per_s")])) is not None and metric.counter:
        return metric
    return next((m for m in _FAMILIES if m.matches(name)), None)


def missing(names: Iterable[str]) -> list[str]:
    """The names :func:`describe` does not know, sorted."""
    return sorted({name for name in names if describe(name) is None})


def section_of(metric: Metric) -> str:
    """Where the page lists ``metric`` (one of :data:`SECTIONS`): the one service that reports it, else "every
    service"."""
    return metric.services[0] if len(metric.services) == 1 else "every service"
