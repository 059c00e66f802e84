"""The catalog of every metric a run publishes in its stats reports: one place where each is declared.

Each :class:`~ebrl.metrics.record.Metric` names a metric (or a family, ``busy/<lane>``), its unit, the services
that report it, what it means and the modules that publish it. ``docs/stats.md``'s table is generated from it
(``python docs/gen.py``), tests check that every record's name is in the source of the modules it names and that
every metric real runs publish is here (``tests/test_metrics.py``), and :func:`describe` looks a published name up::

    >>> describe("sim/env_steps_per_s").meaning
    'environment steps'

Data only: importing it imports neither torch nor zenoh.
"""

from __future__ import annotations

from typing import Iterable

from ebrl.metrics import alloc, common, evaluation, gen, launcher, observers, replay, sim, train
from ebrl.metrics.record import Metric

__all__ = ["CATALOG", "EVERY", "SECTIONS", "Metric", "describe", "missing", "section_of"]

EVERY = common.EVERY  # the services that each report what every service reports (the launcher is not one)

CATALOG: tuple[Metric, ...] = (*sim.METRICS, *gen.METRICS, *train.METRICS, *replay.METRICS, *evaluation.METRICS,
                               *alloc.METRICS, *launcher.METRICS, *observers.METRICS, *common.METRICS)

# the page's sections, in order (a service's own metrics, then what every service reports), each with its line
SECTIONS = {
    "sim": "The simulator: env steps, episodes, segments, chunk latencies, core rebinding; and the host's cores and "
           "GPUs (one sim service per host reports them).",
    "gen": "Generation: forward passes, the weights it acts with, the observations waiting for it.",
    "train": "Training: updates, weights, the data it took or refused, the returns it computed from that data, and "
             "the algorithm's numbers of its last update (a user's own algorithm reports its own names beside "
             "these).",
    "replay": "The replay service of an off-policy algorithm (SAC).",
    "eval": "The eval service ([Evaluating](evaluation.md)): one report of its own per evaluated version "
            "(`eval/version` and the results), and periodic ones of what it did.",
    "alloc": "The allocator ([The allocator](allocator.md)): its plan and the measured capacities it re-plans from.",
    "launcher": "The launcher's own report (`launcher/<host>` on each host of a run over several).",
    "log": "The tracking sinks' service ([Tracking](tracking.md)).",
    "viz": "The rerun bridge ([Watching a run](watching.md)).",
    "every service": "What every service reports about itself (and, where it says so, the launcher).",
}

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
