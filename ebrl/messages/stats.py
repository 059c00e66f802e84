"""What services report about themselves (``ebrl/stats/...``): periodic stats, timeline spans, events and the
episodes a simulator finished."""

from __future__ import annotations

from dataclasses import dataclass

from ebrl.messages.common import KIB, MAX_METRICS, MIB, MessageError, doc, in_range


@dataclass
class StatsReport:
    """Periodic stats of one service instance, published every `stats_interval` seconds."""

    KEY = "ebrl/stats/<run>/<service>/<instance>"
    run: str = doc("run name")
    service: str = doc("service role: sim, gen, train, ...")
    instance: int = doc("instance index of the service")
    time: float = doc("epoch seconds of the report")
    seq: int = doc("report counter of this instance, from 0")
    metrics: dict[str, float] = doc("namespaced metrics, e.g. sim/env_steps_per_s (see docs/stats.md)")

    MAX_BYTES = 1 * MIB

    def check(self) -> None:
        in_range("StatsReport.instance", self.instance, 0, 1 << 20)
        if len(self.metrics) > MAX_METRICS:
            raise MessageError(f"StatsReport: {len(self.metrics)} metrics, more than {MAX_METRICS}")


@dataclass
class SpanBatch:
    """Timeline spans of one lane, batched (a service publishes each lane every 0.2 s): span i was busy
    with ``label[i]`` from ``start[i]`` to ``end[i]``."""

    KEY = "ebrl/stats/<run>/spans/<lane>"
    lane: str = doc("timeline lane, e.g. sim.g0, gen, train, weights")
    service: str = doc("service role that recorded the spans")
    instance: int = doc("instance index of that service")
    start: list[float] = doc("epoch seconds, one per span")
    end: list[float] = doc("epoch seconds, one per span")
    label: list[str] = doc("what ran, one per span: chunk, wait, forward, update, v<version>")

    MAX_BYTES = 1 * MIB  # at most SPAN_BATCH_MAX spans, about 120 KB

    def __post_init__(self) -> None:
        if not len(self.start) == len(self.end) == len(self.label):
            raise MessageError(f"SpanBatch: start, end and label differ in length "
                               f"({len(self.start)}, {len(self.end)}, {len(self.label)})")

    def spans(self) -> list["Span"]:
        return [Span(self.lane, a, b, label, self.service, self.instance)
                for a, b, label in zip(self.start, self.end, self.label)]


@dataclass
class Span:
    """One span of a :class:`SpanBatch`, as readers use it (not a wire message of its own)."""

    lane: str
    start: float
    end: float
    label: str
    service: str
    instance: int


@dataclass
class Event:
    """Something worth a line in the run's event log: a service came up, re-allocation, restart, ..."""

    KEY = "ebrl/stats/<run>/events/<service>"
    time: float = doc("epoch seconds")
    service: str = doc("service role that reports it")
    instance: int = doc("instance index of that service")
    kind: str = doc("short machine-readable kind, e.g. live, exited, quota, affinity, realloc")
    text: str = doc("one human-readable line")

    MAX_BYTES = 256 * KIB


RETURN_WINDOW = 20  # the latest episodes behind a reported mean return or success rate (sim's, train's)
EPISODES_MAX = 1024  # most records in one EpisodeBatch; a simulator finishing more per interval counts the rest


@dataclass
class EpisodeBatch:
    """Every episode one simulator instance finished since its previous batch, one record each (sim -> anyone):
    the per-episode returns and successes behind ``sim/episode_return_mean`` and ``sim/success_rate``. Published
    with the instance's stats report, at most ``EPISODES_MAX`` records (the oldest beyond are dropped and
    counted as ``sim/episode_records_dropped``); the lists are parallel, one entry per episode."""

    KEY = "ebrl/stats/<run>/episodes/<service>"
    service: str = doc("service role that ran the episodes (sim)")
    instance: int = doc("instance index of that service (the host's number)")
    env_id: list[int] = doc("global env id")
    episode: list[int] = doc("index of the episode among that env's, from 0")
    returns: list[float] = doc("undiscounted return of the episode")
    length: list[int] = doc("env steps of the episode")
    success: list[bool | None] = doc("the task's success check at the episode's end; null where the task has none")
    policy_version: list[int] = doc("policy version of the chunk that ended the episode")
    env_steps: list[int] = doc("env steps this instance had run when the episode ended (its sim/env_steps)")
    end_time: list[float] = doc("epoch seconds when the episode ended")

    MAX_BYTES = 1 * MIB

    def __post_init__(self) -> None:
        lengths = {len(getattr(self, f)) for f in ("env_id", "episode", "returns", "length", "success",
                                                    "policy_version", "env_steps", "end_time")}
        if len(lengths) != 1:
            raise MessageError("EpisodeBatch: the per-episode lists differ in length")
        if lengths.pop() > EPISODES_MAX:
            raise MessageError(f"EpisodeBatch: more than {EPISODES_MAX} episodes")
