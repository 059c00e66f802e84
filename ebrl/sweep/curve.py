"""A trial's learning curve: the objective metric at each training update, read from the run's stats reports,
and the one value a trial is judged by (the curve reduced: its last point, its best, the mean of its last N).

The step of a point is the number of training updates done (``train/updates`` of training's rank 0) when the
report carrying the metric arrived; updates that passed between two reports take the later value, so that every
step has a point and trials compare at the same steps (Optuna's pruners compare intermediate values step by
step). Pure: fed :class:`~ebrl.messages.StatsReport` objects, live (``ebrl.watch``) or from a recording."""

from __future__ import annotations

import difflib
import math
from typing import Iterable

from ebrl.messages import StatsReport
from ebrl.sweep.spec import Objective


class Curve:
    """The points of one run's curve (step -> the latest value seen at that step) as reports are fed."""

    def __init__(self, objective: Objective):
        self.objective = objective
        self.points: dict[int, float] = {}
        self.updates = 0  # training updates done, as the latest training report says
        self.env_steps = 0  # env steps training took
        self.reported = -1  # the last step handed to Optuna (:meth:`new_steps`)
        self.metrics_seen: set[str] = set()  # of the objective's service: said when the metric never came

    def feed(self, report: StatsReport) -> None:
        """Take one stats report (any service: only those that carry the metric, or training's counts, matter)."""
        metrics = report.metrics
        if report.service == "train" and report.instance == 0:
            self.updates = int(metrics.get("train/updates", metrics.get("train/policy_version", self.updates)))
            self.env_steps = int(metrics.get("train/env_steps", self.env_steps))
        source = self.objective.source
        if source is not None and report.service != source:
            return
        self.metrics_seen.update(metrics)
        value = metrics.get(self.objective.metric)
        if value is not None and math.isfinite(value):
            self.points[self.updates] = float(value)

    def feed_all(self, reports: Iterable[StatsReport]) -> "Curve":
        for report in reports:
            self.feed(report)
        return self

    def value(self) -> float | None:
        """The objective of the curve so far: what the trial scores if the run ended now (None: no point yet)."""
        return reduce(self.points, self.objective)

    def new_steps(self) -> list[int]:
        """Steps not yet handed to Optuna up to the latest point (marked handed): every step between, so that a
        pruner finds each trial at every step. Their value is :meth:`value` now."""
        if not self.points:
            return []
        latest = max(self.points)
        steps = list(range(max(self.reported + 1, min(self.points)), latest + 1))
        self.reported = max(self.reported, latest)
        return steps

    def missing(self) -> str:
        """Why the curve is empty: the metric was never published; the closest names that were."""
        close = difflib.get_close_matches(self.objective.metric, sorted(self.metrics_seen), 3, 0.5)
        where = f"by {self.objective.source}" if self.objective.source else "by any service"
        hint = f" (closest published: {', '.join(close)})" if close else ""
        return (f"objective metric {self.objective.metric} was never published {where} during the run "
                f"({self.updates} training updates){hint}; docs/stats.md lists the metrics")


def reduce(points: dict[int, float], objective: Objective) -> float | None:
    """``points`` (step -> value) to one value as ``objective.reduce`` says (None where there are none)."""
    if not points:
        return None
    ordered = [points[step] for step in sorted(points)]
    if objective.reduce == "last":
        return ordered[-1]
    if objective.reduce == "best":
        return max(ordered) if objective.direction == "maximize" else min(ordered)
    tail = ordered[-objective.last_n:]
    return sum(tail) / len(tail)


def report_and_check(trial, curve: Curve) -> bool:
    """Hand the curve's new steps to an Optuna trial (``trial.report(value, step)``) and ask its pruner;
    True where the trial should be pruned."""
    steps = curve.new_steps()
    value = curve.value()
    for step in steps:
        trial.report(value, step)
    return bool(steps) and trial.should_prune()
