"""The service graph: what each role publishes, subscribes to, queries and answers on the bus, in one place.

Sample Factory's ``connect_components`` and dora-rs's dataflow file show at a glance who talks to whom; this
is EBRL's. Each :class:`Flow` names a key pattern (built by ``ebrl.keys``, so the keys themselves stay
in one module) and the message it carries. From it:

* a test records every key each service touches over a real run on the in-memory bus and fails when a role
  uses a key its flows do not declare (``tests/test_graph.py``);
* ``ebrl graph`` prints it, and ``docs/graph.md`` (the graph as a Mermaid chart and a table) is generated
  from it (:func:`markdown`; the test checks it is current);
* the bus's access rules are generated from it (:func:`access_control`: Zenoh's ACL in which each role's
  identity may send only what its flows declare, enforced where every sender's identity is known, a router;
  a test runs it on one). Every run's launcher enforces them on the services that are its clients
  (``bus.mode = "client"``, the default; ``ebrl.bus.auth``).

Patterns: ``{run}`` is the run's name, ``{role}`` and ``{instance}`` the service's own; ``*`` matches one
key chunk, ``**`` any number (Zenoh's key expressions). Every service has :data:`SERVICE_FLOWS` (its stats,
spans, events, liveliness and its control keys) besides its own.
"""

from __future__ import annotations

import functools
import inspect
from dataclasses import dataclass
from typing import Any, Callable, Literal

from ebrl import keys
from ebrl.metric import Metric

Direction = Literal["put", "sub", "query", "answer", "token", "watch"]
DIRECTIONS: tuple[Direction, ...] = ("put", "sub", "query", "answer", "token", "watch")
VERBS = {"put": "publishes", "sub": "subscribes to", "query": "queries", "answer": "answers queries on",
         "token": "holds the liveliness token", "watch": "watches liveliness on"}


@dataclass(frozen=True)
class Flow:
    """One edge end: ``direction`` on the keys of ``key`` (a builder of ``ebrl.keys`` and its arguments, the
    placeholders :data:`R`, :data:`ROLE` and :data:`I` among them), carrying ``message``; ``name`` is what code asks
    a role's :class:`RoleKeys` for (``keys_of(run, "sim", 0).put("obs", group=3)``)."""

    name: str
    direction: Direction
    key: tuple  # (builder, *arguments): ``(keys.obs, R)``
    message: str
    why: str = ""
    chart: bool = True  # drawn in the chart (a monitor that only counts what it hears is not)
    # its one ``*`` chunk is a group of the environment: an instance's identity may send it for its own groups
    # alone where the router knows them (sim/n has groups n*G .. n*G+G-1: ebrl.sched.fleet)
    grouped: bool = False

    @property
    def pattern(self) -> str:
        """The flow's key expression, placeholders left in: ``ebrl/data/{run}/obs/*``."""
        return self.key[0](*self.key[1:])

    def build(self, run: str | None, role: str, instance: int | str, given: dict[str, object]) -> str | None:
        """The concrete key of this flow for one run, role and instance, with the builder's arguments ``given``
        in place of the declared ones; None where that key is outside the flow's pattern. The run, where the
        holder has one, narrows a flow of every run (an observer's)."""
        builder, *declared = self.key
        args = _declared(self.key)
        fill = {R: run, ROLE: role, I: instance}
        args = {name: fill.get(value, value) if isinstance(value, str) else value for name, value in args.items()}
        if run is not None and "run" in args:
            args["run"] = run
        if run is None and R in declared:
            raise ValueError(f"{role}'s flow {self.name!r} is of one run: keys_of(run, ...) needs the run's name")
        key = builder(**{**args, **given})
        pattern = self.pattern.replace(R, run or "*").replace(ROLE, role).replace(I, str(instance))
        return key if covers(pattern, key) else None


@functools.lru_cache(maxsize=None)
def _declared(key: tuple) -> dict[str, object]:
    """A flow's declared arguments by the builder's parameter names: ``(keys.obs, R)`` -> ``{"run": R}``."""
    return dict(inspect.signature(key[0]).bind(*key[1:]).arguments)


R, ROLE, I = "{run}", "{role}", "{instance}"
EVERY_STAT = "StatsReport | SpanBatch | Event | EpisodeBatch"  # what ebrl/stats/<run>/** carries

SERVICE_FLOWS = (  # every service (ebrl.service.Service)
    Flow("stats", "put", (keys.stats, R, ROLE, I), "StatsReport", "its stats report, every run.stats_interval"),
    Flow("spans", "put", (keys.spans, R, "*"), "SpanBatch", "timeline spans of its lanes"),
    Flow("events", "put", (keys.events, R, ROLE), "Event", "what happened: a restart, a decision, a device"),
    Flow("ctl", "sub", (keys.ctl, R, ROLE, I, "*"), "Quota | Affinity | Stop", "the allocator's and launcher's "
         "control"),
    Flow("status", "answer", (keys.ctl, R, ROLE, I, "status"), "StatsReport", "its latest numbers, on request"),
    Flow("live", "token", (keys.live, R, ROLE, I), "-", "alive while the process runs"),
)

WEIGHTS_READER = (  # ebrl.weights.WeightsReceiver: new versions as published, and the newest on request
    Flow("weights", "sub", (keys.weights_all, R), "Weights | WeightsPart", "new policy versions"),
    Flow("weights", "query", (keys.weights_all, R), "Weights | WeightsPart", "the newest version, at start"),
    Flow("stats", "sub", (keys.stats, R, "train", 0), "StatsReport", "training's version (back from a forged one)"),
)

STAGES = ("sim", "gen", "train")  # what the allocator plans


@dataclass(frozen=True)
class Switch:
    """The setting that turns a service on or off (:attr:`Role.switch`). ``setting`` names it for a user (``ebrl up
    --only`` says it of a service the config has off); ``on(cfg)`` reads it from a run's ``ebrl.config.Config``,
    by attribute alone, since the graph sits below the config."""

    setting: str
    on: Callable[[Any], bool]


@dataclass(frozen=True)
class Role:
    """One role of a run, with every fact about it that other modules read.

    ``flows``: what it sends and reads on the bus. For a service (an ``ebrl.service.Service``, ``start`` given):
    its place in a host's start order (``ebrl.config.ROLES``: lower starts first) and the module the launcher runs
    for it (``python -m <module>``). ``stats``: the namespace of its own metrics (``sim/env_steps``: ``sim``), and
    ``about``, that namespace's line in docs/stats.md; ``metrics``, the records of the metrics it reports that no
    module of the catalog (``ebrl/metrics/``, the stock services') declares. ``optional``: no other service needs
    it (its death, where restarts do not mend it, never ends the run). ``switch``: the setting that turns it on
    (None: every run has it). ``with_train``: it starts on the host that trains unless a ``[hosts]`` entry names
    it. Adding a service is its module, its record here and its tests (docs/contributing.md: "A new service")."""

    name: str
    flows: tuple[Flow, ...]
    start: int | None = None  # None: not a service (the launcher, observers)
    stats: str = ""  # the namespace of its own metrics; "": it reports none
    about: str = ""  # the line of its metrics' section in docs/stats.md
    metrics: tuple[Metric, ...] = ()  # its own metrics' records, where ebrl/metrics/ has no module of them
    optional: bool = False  # a service no other one needs (ebrl.launch.OPTIONAL_ROLES)
    switch: Switch | None = None  # None: every run has it
    with_train: bool = False  # on training's host (ebrl.hosts.plan)

    @property
    def service(self) -> bool:
        """Whether it is an ``ebrl.service.Service`` (it then has :data:`SERVICE_FLOWS` too)."""
        return self.start is not None

    @property
    def module(self) -> str:
        """What the launcher runs for a service: ``ebrl.services.<name>``; "" for a role that is no service."""
        return f"ebrl.services.{self.name}" if self.service else ""


def _sinks_on(cfg: Any) -> bool:
    return bool(cfg.log.tensorboard or cfg.log.csv or cfg.log.wandb)


ROLES: dict[str, Role] = {role.name: role for role in (
    Role("sim", start=5, stats="sim", about="The simulator: env steps, episodes, segments, chunk latencies, core "
         "rebinding; and the host's cores and GPUs (one sim service per host reports them).", flows=(
        Flow("obs", "put", (keys.obs, R), "Observation", "a group's observations, when its chunk ends",
             grouped=True),
        Flow("traj", "put", (keys.traj, R), "TrajectorySegment", "finished segments", grouped=True),
        Flow("packed", "put", (keys.traj_packed, R), "SegmentBatch", "a vectorized group's finished segments, "
             "packed", grouped=True),
        Flow("episodes", "put", (keys.episodes, R, ROLE), "EpisodeBatch", "finished episodes (returns, success)"),
        Flow("act", "sub", (keys.act, R), "ActionChunk", "each group's next chunk"),
        Flow("live", "watch", (keys.live_all, R), "-", "which gen and sim hosts are up (the iteration gate)"),
    )),
    Role("gen", start=4, stats="gen", about="Generation: forward passes, the weights it acts with, the observations "
         "waiting for it.", flows=(
        Flow("obs", "sub", (keys.obs, R), "Observation", "the groups' observations"),
        Flow("act", "put", (keys.act, R), "ActionChunk", "a chunk per group"),
        *WEIGHTS_READER,
        Flow("live", "watch", (keys.live, R, "sim"), "-", "how many sim hosts serve (a batch's size)"),
    )),
    Role("train", start=3, stats="train", about="Training: updates, weights, the data it took or refused, the returns "
         "it computed from that data, and the algorithm's numbers of its last update (a user's own algorithm reports "
         "its own names beside these).", flows=(
        Flow("traj", "sub", (keys.traj, R), "TrajectorySegment", "segments to learn from"),
        Flow("packed", "sub", (keys.traj_packed, R), "SegmentBatch", "packed segments to learn from"),
        Flow("weights", "put", (keys.weights, R), "Weights", "each new version (small policies)"),
        Flow("parts", "put", (keys.weights_parts, R), "WeightsPart", "each new version in parts (large policies)"),
        Flow("weights", "answer", (keys.weights_all, R), "Weights | WeightsPart", "the newest version, on request"),
        Flow("request", "put", (keys.replay, R, "request"), "ReplayRequest", "an update's new transitions, "
             "minibatches wanted (an off-policy algorithm)"),
        Flow("sample", "sub", (keys.replay, R, "sample"), "ReplaySample", "the minibatches of its gradient steps"),
    )),
    Role("replay", start=2, stats="replay", about="The replay service of an off-policy algorithm (SAC).",
         switch=Switch("algo.name: an off-policy algorithm", lambda cfg: cfg.algo.uses_replay), with_train=True,
         flows=(
        Flow("request", "sub", (keys.replay, R, "request"), "ReplayRequest", "transitions to keep, minibatches to "
             "draw"),
        Flow("sample", "put", (keys.replay, R, "sample"), "ReplaySample", "minibatches drawn uniformly"),
    )),
    Role("eval", start=6, stats="eval", about="The eval service ([Evaluating](evaluation.md)): one report of its own "
         "per evaluated version (`eval/version` and the results), and periodic ones of what it did.", optional=True,
         switch=Switch("eval.every > 0", lambda cfg: cfg.eval.every > 0), with_train=True, flows=WEIGHTS_READER),
    Role("alloc", start=7, stats="alloc", about="The allocator ([The allocator](allocator.md)): its plan and the "
         "measured capacities it re-plans from.", switch=Switch("alloc.enabled", lambda cfg: cfg.alloc.enabled),
         with_train=True, flows=(
        Flow("stats", "sub", (keys.stats, R, "sim", "*"), "StatsReport", "every simulator's rates and CPU use"),
        Flow("stats", "sub", (keys.stats, R, "gen", 0), "StatsReport", "generation's rates and CPU use"),
        Flow("stats", "sub", (keys.stats, R, "train", 0), "StatsReport", "training's rates and CPU use"),
        *(Flow("quota", "put", (keys.ctl, R, stage, "*", "quota"), "Quota", "threads, batch and GPU memory of a "
               "stage") for stage in STAGES),
        *(Flow("affinity", "put", (keys.ctl, R, stage, "*", "affinity"), "Affinity", "a stage's cores")
          for stage in STAGES),
        Flow("gpu_share", "put", (keys.gpu_share, R, "*"), "GpuShare", "a stage's new GPU share, for its host's "
             "launcher"),
    )),
    Role("log", start=1, stats="log", about="The tracking sinks' service ([Tracking](tracking.md)).", optional=True,
         switch=Switch("[log]: tensorboard, csv or wandb", _sinks_on), with_train=True, flows=(
        Flow("stats", "sub", (keys.stats_all, R), EVERY_STAT, "everything, for the sinks"),)),
    Role("observer", flows=(  # a script or `ebrl stats` signed in as observer (ebrl.stats.observer_config): it
        # reads only, the stats of any run on the bus (its file names no run: `ebrl stats` without --run watches
        # every one)
        Flow("stats", "sub", (keys.stats_all, None), EVERY_STAT, "a run watched from any script", chart=False),
        Flow("live", "watch", (keys.live, "*", "launcher", "*"), "-", "whether a run's launchers are up "
             "(the end of ebrl.stats.stream)", chart=False),
    )),
    Role("viz", start=0, stats="viz", about="The rerun bridge ([Watching a run](watching.md)).",
         switch=Switch("viz.rerun not off", lambda cfg: cfg.viz.rerun != "off"), with_train=True, flows=(
        Flow("stats", "sub", (keys.stats_all, R), EVERY_STAT, "everything, for rerun"),)),
    Role("launcher", stats="launcher", about="The launcher's own report (`launcher/<host>` on each host of a run "
         "over several).", flows=(
        Flow("stats", "sub", (keys.stats_all, R), EVERY_STAT, "the progress line, "
             "the recording"),
        Flow("stats", "put", (keys.stats, R, "launcher", I), "StatsReport", "its own report"),
        Flow("events", "put", (keys.events, R, "launcher"), "Event", "live, stall, auto, host, stopping"),
        Flow("stop", "put", (keys.ctl, R, "*", "*", "stop"), "Stop", "the end of the run, to every service"),
        Flow("gpu_share", "sub", (keys.gpu_share, R, I), "GpuShare", "a stage of this host to restart with a new "
             "GPU share"),
        Flow("stop", "sub", (keys.ctl, R, "launcher", "*", "stop"), "Stop", "the primary host ended the run"),
        Flow("ctl", "sub", (keys.ctl, R, "*", "*", "*"), "Quota | Affinity | Stop", "counts control for services "
             "the run does not have", chart=False),
        Flow("live", "token", (keys.live, R, "launcher", I), "-", "this host's launcher is up"),
        Flow("live", "watch", (keys.live_all, R), "-", "which services and hosts are up"),
    )),
)}
FLOWS: dict[str, tuple[Flow, ...]] = {name: role.flows for name, role in ROLES.items()}
SERVICES = tuple(name for name, role in ROLES.items() if role.service)  # roles that are ebrl.service.Service
START_ORDER = tuple(sorted(SERVICES, key=lambda name: ROLES[name].start))  # every service a host can run


def flows(role: str) -> tuple[Flow, ...]:
    """Every flow of ``role``: its own, and those every service has."""
    return FLOWS[role] + (SERVICE_FLOWS if role in SERVICES else ())


class RoleKeys:
    """The concrete keys of one role's flows in one run (:func:`keys_of`): ``put``, ``sub``, ``query``, ``answer``,
    ``token`` and ``watch`` each take a flow's name and the key builder's arguments that the flow leaves open
    (``put("obs", group=3)``, ``put("stop", service="sim", instance=0)``), and return the key, or raise ValueError
    where the role declares no such flow in that direction or the key is outside it. Code gets its keys here
    alone, so that a key it uses is one the graph declares (and the access rules allow)."""

    def __init__(self, run: str | None, role: str, instance: int | str, own: tuple[Flow, ...]):
        self.run, self.role, self.instance, self.flows = run, role, instance, own
        self._built: dict[tuple, str] = {}

    def _key(self, direction: Direction, name: str, given: dict[str, object]) -> str:
        memo = (direction, name, *sorted(given.items()))
        if (found := self._built.get(memo)) is not None:
            return found
        candidates = [f for f in self.flows if f.name == name and f.direction == direction]
        if not candidates:
            declared = sorted({f.name for f in self.flows if f.direction == direction}) or ["none"]
            raise ValueError(f"{self.role} declares no flow {name!r} it {VERBS[direction]} (ebrl/graph.py); its "
                             f"flows in that direction: {', '.join(declared)}")
        for flow in candidates:
            if (key := flow.build(self.run, self.role, self.instance, given)) is not None:
                self._built[memo] = key
                return key
        raise ValueError(f"{self.role}/{self.instance}: {given} is outside its flow {name!r} "
                         f"({', '.join(f.pattern for f in candidates)})")

    def put(self, name: str, **given: object) -> str:
        return self._key("put", name, given)

    def sub(self, name: str, **given: object) -> str:
        return self._key("sub", name, given)

    def query(self, name: str, **given: object) -> str:
        return self._key("query", name, given)

    def answer(self, name: str, **given: object) -> str:
        return self._key("answer", name, given)

    def token(self, **given: object) -> str:
        return self._key("token", "live", given)

    def watch(self, name: str = "live", **given: object) -> str:
        return self._key("watch", name, given)


@functools.lru_cache(maxsize=4096)
def keys_of(run: str | None, role: str, instance: int | str = 0, service: bool = False) -> RoleKeys:
    """The keys ``role`` (its instance ``instance``) uses in run ``run`` (None: an observer's of every run).
    ``service``: a :class:`~ebrl.service.Service` whose role the graph may lack (a test's own), which then has the
    flows every service has alone."""
    if role not in FLOWS and not service:
        raise ValueError(f"no role {role!r} in the service graph (ebrl/graph.py); roles are {', '.join(FLOWS)}")
    return RoleKeys(run, role, instance, flows(role) if role in FLOWS else SERVICE_FLOWS)


def every_token() -> str:
    """What ``ebrl router`` watches to print the services that join and leave: the liveliness tokens of every
    run. The router is no role of any run (it takes part in none and signs in as none), so it has no flows."""
    return keys.live_all()


def _chunks_match(pattern: list[str], key: list[str]) -> bool:
    if not pattern:
        return not key
    if pattern[0] == "**":
        return any(_chunks_match(pattern[1:], key[i:]) for i in range(len(key) + 1))
    return bool(key) and pattern[0] in ("*", key[0]) and _chunks_match(pattern[1:], key[1:])


def covers(pattern: str, key: str) -> bool:
    """Whether the key expression ``pattern`` includes every key of ``key`` (a key, or a pattern: a
    subscription on ``ebrl/data/r/obs/*`` is covered by ``ebrl/data/r/obs/*`` and by ``ebrl/data/r/**``)."""
    return _chunks_match(pattern.split("/"), key.split("/"))


def allowed(role: str, instance: int | str, direction: Direction, key: str, run: str) -> bool:
    """Whether ``role`` (its instance ``instance``) declares ``direction`` on ``key`` in run ``run``."""
    for flow in flows(role):
        if flow.direction != direction:
            continue
        pattern = flow.pattern.replace(R, run).replace(ROLE, role).replace(I, str(instance))
        if covers(pattern, key):
            return True
    return False


def text() -> str:
    """The graph as plain lines, one per flow: ``gen  subscribes to  ebrl/data/{run}/obs/*  Observation``."""
    rows = [(role, VERBS[f.direction], f.pattern, f.message) for role in FLOWS for f in flows(role)]
    widths = [max(len(r[i]) for r in rows) for i in range(3)]
    return "".join(f"{a:<{widths[0]}}  {b:<{widths[1]}}  {c:<{widths[2]}}  {d}\n" for a, b, c, d in rows)


STATS_PLANE = ("StatsReport", "SpanBatch", "Event", "EpisodeBatch")  # every service's; drawn as one edge


def markdown() -> str:
    """``docs/graph.md``: the graph as a Mermaid chart (data and control between the roles) and every flow."""
    lines, seen = ["```mermaid", "flowchart LR"], set()
    for writer in FLOWS:
        for put in (f for f in flows(writer) if f.direction == "put" and not f.message.startswith(STATS_PLANE)):
            for reader in FLOWS:
                for sub in flows(reader):
                    edge = (writer, reader, put.message)
                    if reader != writer and sub.direction == "sub" and sub.chart and edge not in seen \
                            and intersects(_instance(put.pattern, writer), _instance(sub.pattern, reader)):
                        seen.add(edge)
                        lines.append(f"    {writer} -- {put.message} --> {reader}")
    readers = [name for name in FLOWS if any(f.direction == "sub" and f.message == EVERY_STAT and f.chart
                                             for f in flows(name))]  # what reads every report: drawn on the right
    writers = [name for name in SERVICES if name not in readers]
    lines += [f"    {' & '.join(writers)} -. stats, spans, events, episodes .-> {' & '.join(readers)}", "```"]
    table = ["| role | direction | key | message | why |", "|---|---|---|---|---|"]
    for role in FLOWS:
        for flow in flows(role):
            table.append(f"| {role} | {VERBS[flow.direction]} | `{flow.pattern}` | {flow.message} | {flow.why} |")
    head = ("# The service graph\n\n<!-- generated by `ebrl graph --markdown` from ebrl/graph.py; do not edit by "
            "hand. -->\n\nWho talks to whom on the bus (`ebrl/graph.py`; a test fails when a service uses a key "
            "its role does not declare). Data and control between the roles; every service also publishes its "
            f"stats, spans and events, which {', '.join(readers[:-1])} and {readers[-1]} read:\n\n")
    return head + "\n".join(lines) + "\n\n" + services_markdown() + "\nEvery flow, by role (`{run}`: the run's " \
        "name, `{role}`/`{instance}`: the service's own; `*` one key chunk, `**` any number):\n\n" + \
        "\n".join(table) + "\n"


def services_markdown() -> str:
    """The services' table of ``docs/graph.md``: start order, the setting that turns each on, where it runs."""
    rows = ["The services, in a host's start order (each a `python -m ebrl.services.<role>`, or a thread of a "
            "process several share: [Services and processes](processes.md)):", "",
            "| service | runs when | on which host | if it dies | its own metrics |", "|---|---|---|---|---|"]
    for name in START_ORDER:
        role = ROLES[name]
        when = role.switch.setting if role.switch else "always"
        host = "the one that trains, unless a `[hosts]` entry names it" if role.with_train else \
            "where `[hosts]` or `--only` puts it"
        dies = "restarted (`run.max_restarts`), then the run goes on without it" if role.optional else \
            "restarted (`run.max_restarts`), then the run stops"
        stats = f"`{role.stats}/*`" if role.stats else "-"
        rows.append(f"| {name} | {when} | {host} | {dies} | {stats} |")
    return "\n".join(rows) + "\n"


SENDS: tuple[Direction, ...] = ("put", "answer", "token")  # what acts on the run
READS: tuple[Direction, ...] = ("sub", "query", "watch")


def rights_markdown() -> str:
    """Which identity may do what on a run's bus, as a Markdown table (README's security section and
    ``docs/security.md``): the keys each may send on and those it may read, from :data:`FLOWS` (what
    :func:`access_control` enforces at the launcher). Keys are shortened to ``<plane>/<rest>`` (the run's name
    left out), an instance is ``*``."""
    def short(pattern: str, role: str) -> str:
        chunks = pattern.replace(ROLE, role).replace(I, "*").split("/")
        if len(chunks) > 3 and chunks[2] in (R, "*"):
            return "/".join(chunks[1:2] + chunks[3:])
        return "/".join(chunks[1:])  # ebrl/<plane>/**: every run's

    def keys_of(role: str, directions: tuple[Direction, ...], own: tuple[Flow, ...]) -> str:
        found = sorted({short(f.pattern, role) for f in own if f.direction in directions})
        return ", ".join(f"`{k}`" for k in found) or "nothing"

    every = ", ".join(f"`{short(f.pattern, '<role>')}`" for f in SERVICE_FLOWS if f.direction in SENDS)
    rows = ["| identity | may send (publish, answer, hold a token) | may read (subscribe, query, watch) |",
            "|---|---|---|",
            f"| every service (`ebrl-<role>`) | its own {every} | `ctl/<role>/*/*` (its control) |"]
    for role in FLOWS:
        sends = keys_of(role, SENDS, FLOWS[role])
        if role == ROUTING_ROLE:
            sends = f"anything (it routes what the services of other hosts were allowed to send); itself: {sends}"
        rows.append(f"| `{username(role)}` | {sends} | {keys_of(role, READS, FLOWS[role])} |")
    return "\n".join(rows) + "\n"


# What a peer of each direction sends on the keys of its flows, in Zenoh's ACL words: a publisher sends puts, a
# subscriber its subscription's declaration, an asker queries, an answerer its queryable and the replies, a
# token holder the token, a watcher its liveliness subscription and queries.
ACL_MESSAGES: dict[Direction, tuple[str, ...]] = {
    "put": ("put",), "sub": ("declare_subscriber",), "query": ("query",), "answer": ("declare_queryable", "reply"),
    "token": ("liveliness_token",), "watch": ("declare_liveliness_subscriber", "liveliness_query")}
ALL_ACL_MESSAGES = sorted({m for ms in ACL_MESSAGES.values() for m in ms} | {"delete"})


def username(role: str) -> str:
    """The Zenoh user name of ``role``'s identity (:func:`access_control`'s subjects, ``ebrl.bus.auth``'s lines):
    ``ebrl-<role>``, and ``observer`` for observers."""
    return "observer" if role == "observer" else f"ebrl-{role}"


ROUTING_ROLE = "launcher"  # a host's launcher routes every role's traffic between hosts: its identity sends all


def access_control(run: str, roles: tuple[str, ...] | None = None, trusted_zids: list[str] | tuple[str, ...] = (),
                   instances: tuple[tuple[str, int], ...] | list[tuple[str, int]] = (), groups: int = 0,
                   planned: tuple[tuple[str, int], ...] | None = None,
                   shares: tuple[tuple[tuple[str, int], ...], ...] = ()) -> dict[str, object]:
    """Zenoh's ``access_control`` block for run ``run``, default deny: what a peer signed in as a role's identity
    (:func:`username`) sends is taken in only where that role's flows declare it (each role's instance chunk
    any instance's: one identity per role); what a session sends out is not filtered, since every receiver
    checks what it takes in. ``roles``: the identities to admit (default: every role of the graph). Another
    host's launcher (:data:`ROUTING_ROLE`) forwards what its own clients were allowed to send, so its identity,
    and the sessions with the Zenoh ids ``trusted_zids`` (the far ends of links this router opened itself,
    which identify no user), may send anything.

    ``instances`` (``(role, n)`` pairs: the services a client-mode launcher starts): each signs in as
    :func:`instance_username` and takes in only its own instance's keys (``{instance}`` is ``n``: its token,
    stats, status and control), and with ``groups`` (a simulator's groups) a simulator's data only on its own
    groups' keys; the services' role identities are then not admitted (no process signs in with one), only
    those of the roles that are not services (the launcher, observers).

    ``planned`` (with ``instances``: every instance of the run on every host, launchers included, where the run's
    plan names them): an instance may then declare a liveliness token anywhere in the run's ``live`` keys but on
    another planned instance's, and tokens leave this router only on planned instances' keys. A token of an
    instance the run does not have thus reaches this router's own session alone, where its launcher counts it
    (``launcher/unknown_instances``), and no other process sees it; one on a real instance's key is refused
    where it enters. Without ``planned`` (hosts that join by ``--only``: no plan names the others), an instance
    declares its own token only, and Zenoh drops any other uncounted.

    ``shares``: processes of several services (``run.processes``; each the instances in it, the first of which
    is in ``instances`` and signs in for all): that identity may send what each service of its process may."""
    every = {"id": "anything", "permission": "allow", "flows": ["ingress"], "messages": ALL_ACL_MESSAGES,
             "key_exprs": ["**"]}
    counted = bool(instances) and planned is not None  # tokens of unplanned instances stop here, counted
    real = sorted({keys.live(run, role, int(n)) for role, n in planned or ()})
    rules = _egress_rules(real if counted else None) + [every]
    sending = [str(rule["id"]) for rule in rules if rule is not every]
    subjects, policies = [], []
    admitted = [(role, None) for role in roles or tuple(FLOWS) if not instances or role not in SERVICES]
    for role, instance in admitted + [(role, int(n)) for role, n in instances]:
        subject = role if instance is None else f"{role}-{instance}"
        subjects.append({"id": subject, "usernames": [username(role) if instance is None
                                                      else instance_username(role, instance)]})
        if role == ROUTING_ROLE:
            policies.append({"id": subject, "rules": ["anything"], "subjects": [subject]})
            continue
        members = next((share for share in shares if share[0] == (role, instance)), ((role, instance),))
        ids = [rule for member, n in members
               for rule in _subject_rules(rules, f"{member}-{n}" if instance is not None else subject, run, member,
                                          n, groups, counted)]
        own = {keys.live(run, member, n) for member, n in members}
        if counted and instance is not None and (others := [k for k in real if k not in own]):
            ids.append(f"{subject}-impersonate")  # deny wins over allow in Zenoh's access control
            rules.append({"id": ids[-1], "permission": "deny", "flows": ["ingress"],
                          "messages": ["liveliness_token"], "key_exprs": others})
        policies.append({"id": subject, "rules": ids, "subjects": [subject]})
    if trusted_zids:
        subjects.append({"id": "opened", "zids": list(trusted_zids)})
        policies.append({"id": "opened", "rules": ["anything"], "subjects": ["opened"]})
    subjects.append({"id": "anyone"})  # no attribute: every peer
    policies.append({"id": "send", "rules": sending, "subjects": ["anyone"]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects,
            "policies": policies}


def _egress_rules(real: list[str] | None) -> list[dict[str, object]]:
    """What this router sends on: everything, or with ``real`` (the run's planned tokens) liveliness tokens only
    on those keys."""
    if real is None:
        return [{"id": "send", "permission": "allow", "flows": ["egress"], "messages": ALL_ACL_MESSAGES,
                 "key_exprs": ["**"]}]
    return [{"id": "send", "permission": "allow", "flows": ["egress"], "key_exprs": ["**"],
             "messages": [m for m in ALL_ACL_MESSAGES if m != "liveliness_token"]},
            {"id": "send-tokens", "permission": "allow", "flows": ["egress"], "messages": ["liveliness_token"],
             "key_exprs": real}]


def _subject_rules(rules: list[dict[str, object]], prefix: str, run: str, role: str, instance: int | None,
                   groups: int, counted: bool) -> list[str]:
    """Append to ``rules`` what ``role`` (or its ``instance``) may send, ids starting with ``prefix``; their ids.
    ``counted``: its tokens anywhere in the run's ``live`` keys (:func:`access_control`'s ``planned``; the real
    instances' denied apart), else its own alone."""
    ids = []
    for direction in DIRECTIONS:
        exprs = sorted({e for f in flows(role) if f.direction == direction
                        for e in _concrete(f, run, role, instance, groups)})
        if direction == "token" and instance is not None and counted:
            exprs = [keys.live_all(run)]  # anywhere but on another real instance's key (denied apart)
        if exprs:
            ids.append(f"{prefix}-{direction}")
            rules.append({"id": ids[-1], "permission": "allow", "flows": ["ingress"],
                          "messages": list(ACL_MESSAGES[direction]), "key_exprs": exprs})
    return ids


def _concrete(flow: Flow, run: str, role: str, instance: int | None = None, groups: int = 0) -> list[str]:
    """A flow's key expressions for one run and role: any instance (``instance`` None), or that instance's,
    and a simulator's data on its own groups (``groups`` per host) when the flow is :attr:`Flow.grouped`."""
    def concrete(pattern: str) -> str:
        return pattern.replace(R, run).replace(ROLE, role).replace(I, "*" if instance is None else str(instance))

    if instance is None or not groups or not flow.grouped:
        return [concrete(flow.pattern)]
    chunks = flow.pattern.split("/")
    at = chunks.index("*")  # the group's chunk
    return [concrete("/".join(chunks[:at] + [str(g)] + chunks[at + 1:]))
            for g in range(instance * groups, (instance + 1) * groups)]


def instance_username(role: str, instance: int) -> str:
    """The Zenoh user name of service instance ``role/instance``: ``ebrl-<role>-<instance>`` (``ebrl.bus.auth``
    makes its password)."""
    return f"{username(role)}-{int(instance)}"


def _instance(pattern: str, role: str) -> str:
    return pattern.replace(R, "r").replace(ROLE, role).replace(I, "*")


def intersects(a: str, b: str) -> bool:
    """Whether some key matches both key expressions ``a`` and ``b``."""
    return _meet(a.split("/"), b.split("/"))


def _meet(a: list[str], b: list[str]) -> bool:
    if not a or not b:
        return (not a or a == ["**"]) and (not b or b == ["**"])
    if a[0] == "**":
        return _meet(a[1:], b) or _meet(a, b[1:])
    if b[0] == "**":
        return _meet(a, b[1:]) or _meet(a[1:], b)
    return (a[0] == "*" or b[0] == "*" or a[0] == b[0]) and _meet(a[1:], b[1:])
