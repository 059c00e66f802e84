"""Every Zenoh key EBRL uses, built in one place (shared/DESIGN.md section 3).

Layout: ``ebrl/<category>/<run>/...``. The category comes first so that one
wildcard (``ebrl/stats/**``) sees every run, and so that data subscribers
(``ebrl/data/<run>/**``) never see control or stats traffic. The run name is
in every key: two runs on one bus never see each other's messages.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

ROOT = "ebrl"
CONTROL_KINDS = ("quota", "affinity", "stop", "status", "gpu_share")

_CHUNK = re.compile(r"^[a-z0-9_.=-]+$")


def check_chunk(value: str | int, what: str) -> str:
    """Return ``value`` as one key chunk, or raise ValueError naming ``what``."""
    text = str(value)
    if not _CHUNK.match(text):
        raise ValueError(
            f"{what} {text!r} cannot be a Zenoh key chunk: use lowercase letters, digits and _ . = -"
        )
    return text


# --- data: sim <-> gen <-> train ------------------------------------------------


def obs(run: str, group: int | str = "*") -> str:
    """``ebrl/data/<run>/obs/<group>``: one group's observations at a chunk boundary (sim -> gen)."""
    return f"{ROOT}/data/{run}/obs/{group}"


def act(run: str, group: int | str = "*") -> str:
    """``ebrl/data/<run>/act/<group>``: one group's action chunks (gen -> sim)."""
    return f"{ROOT}/data/{run}/act/{group}"


def traj(run: str, group: int | str = "*") -> str:
    """``ebrl/data/<run>/traj/<group>``: finished trajectory segments (sim -> train)."""
    return f"{ROOT}/data/{run}/traj/{group}"


def traj_packed(run: str, group: int | str = "*") -> str:
    """``ebrl/data/<run>/traj/<group>/packed``: finished segments of many envs in one message (sim -> train), as
    a vectorized group publishes them (``SegmentBatch``); ``traj/**`` reaches both forms."""
    return f"{ROOT}/data/{run}/traj/{group}/packed"


def weights(run: str) -> str:
    """``ebrl/data/<run>/weights``: versioned policy weights (train -> gen), one message per version
    while a version is small (``ebrl.weights``); also answered by the publisher's queryable, so a late
    subscriber never waits for the next update."""
    return f"{ROOT}/data/{run}/weights"


def weights_parts(run: str) -> str:
    """``ebrl/data/<run>/weights/parts``: a large weights version in parts (train -> gen). Under
    ``weights/`` so one expression (:func:`weights_all`) reaches both forms, yet a subscriber of
    :func:`weights` alone never receives a part it cannot use."""
    return f"{ROOT}/data/{run}/weights/parts"


def weights_all(run: str) -> str:
    """``ebrl/data/<run>/weights/**``: whole versions and parts (``**`` also matches ``weights`` itself)."""
    return f"{ROOT}/data/{run}/weights/**"


def replay(run: str, kind: str) -> str:
    """``ebrl/data/<run>/replay/<kind>``: the replay service's exchange with training, ``request`` (train ->
    replay: new transitions and the minibatches wanted) and ``sample`` (replay -> train: the minibatches)."""
    if kind not in REPLAY_KINDS:
        raise ValueError(f"replay key kind {kind!r}: one of {', '.join(REPLAY_KINDS)}")
    return f"{ROOT}/data/{run}/replay/{kind}"


REPLAY_KINDS = ("request", "sample")


def data(run: str) -> str:
    """Every data key of one run."""
    return f"{ROOT}/data/{run}/**"


# --- control: launcher/allocator -> services -------------------------------------


def ctl(run: str, service: str, instance: int | str, kind: str) -> str:
    """``ebrl/ctl/<run>/<service>/<instance>/<kind>``; kind is one of quota, affinity, stop
    (published, versioned, idempotent), status (a queryable answering the service's stats) or gpu_share
    (to a launcher: :func:`gpu_share`)."""
    if kind not in CONTROL_KINDS and kind != "*":
        raise ValueError(f"unknown control kind {kind!r}; expected one of {CONTROL_KINDS}")
    return f"{ROOT}/ctl/{run}/{service}/{instance}/{kind}"


def gpu_share(run: str, host: int | str) -> str:
    """``ebrl/ctl/<run>/launcher/<host>/gpu_share``: the allocator tells the launcher of host ``<host>`` that a
    stage's processes must start again with a new GPU share (``GpuShare``). MPS reads a share only when a
    process makes its CUDA context, so only the launcher, which owns the processes, can apply one; it is told
    on a key of its own, not left to read the stages' ``quota`` messages."""
    return ctl(run, "launcher", host, "gpu_share")


# --- observability ---------------------------------------------------------------


def stats(run: str | None = None, service: str = "*", instance: int | str = "*") -> str:
    """``ebrl/stats/<run>/<service>/<instance>``: periodic stats of one service instance.
    With ``run=None`` the expression matches stats and spans of every run."""
    if run is None:
        return f"{ROOT}/stats/**"
    return f"{ROOT}/stats/{run}/{service}/{instance}"


def spans(run: str, lane: str = "*") -> str:
    """``ebrl/stats/<run>/spans/<lane>``: timeline spans of one lane (``spans`` is reserved
    as a service name so the two families never collide)."""
    return f"{ROOT}/stats/{run}/spans/{lane}"


def events(run: str, service: str = "*") -> str:
    """``ebrl/stats/<run>/events/<service>``: the run's event log (``events`` is reserved too)."""
    return f"{ROOT}/stats/{run}/events/{service}"


def episodes(run: str, service: str = "*") -> str:
    """``ebrl/stats/<run>/episodes/<service>``: per-episode records of the simulators (``episodes`` is reserved
    too); under ``stats/`` so every recorder and sink of ``ebrl/stats/<run>/**`` has them."""
    return f"{ROOT}/stats/{run}/episodes/{service}"


def stats_all(run: str | None) -> str:
    """Everything under ``ebrl/stats/<run>/``: stats reports, spans, events and episode records of one run
    (``run=None``: of every run, ``ebrl/stats/**``)."""
    return f"{ROOT}/stats/{run}/**" if run is not None else f"{ROOT}/stats/**"


def live(run: str, service: str = "*", instance: int | str = "*") -> str:
    """``ebrl/live/<run>/<service>/<instance>``: liveliness token; vanishes when the process dies."""
    return f"{ROOT}/live/{run}/{service}/{instance}"


def live_all(run: str | None = None) -> str:
    """Every liveliness token of one run (``run=None``: of every run)."""
    return f"{ROOT}/live/{run}/**" if run is not None else f"{ROOT}/live/**"


@dataclass(frozen=True)
class Key:
    """A parsed EBRL key; fields that the key's family does not have are ``""`` (``group``: ``None``).

    ============  ==========================================  =========================================
    category      layout                                      fields
    ============  ==========================================  =========================================
    ``data``      ``ebrl/data/<run>/<kind>[/<group>]``         kind (obs, act, traj, weights, replay), group
                  (``traj/<group>/packed`` too)
    ``ctl``       ``ebrl/ctl/<run>/<service>/<instance>/<k>``  service, instance, kind
    ``stats``     ``ebrl/stats/<run>/<service>/<instance>``    service, instance
    ``stats``     ``ebrl/stats/<run>/spans/<lane>``            service = "spans", lane
    ``stats``     ``ebrl/stats/<run>/events/<service>``        service = "events", lane = the publisher
    ``stats``     ``ebrl/stats/<run>/episodes/<service>``      service = "episodes", lane = the publisher
    ``live``      ``ebrl/live/<run>/<service>/<instance>``     service, instance
    ============  ==========================================  =========================================
    """

    category: str
    run: str
    service: str = ""
    instance: str = ""
    kind: str = ""
    group: int | None = None
    lane: str = ""

    @property
    def family(self) -> str:
        """What a ``stats`` key carries: ``spans``, ``events``, ``episodes`` or ``report`` (a service's stats)."""
        return self.service if self.service in RESERVED_STATS else "report"


RESERVED_STATS = ("spans", "events", "episodes")  # stats chunks that are not service names
CATEGORIES = ("data", "ctl", "stats", "live")


def parse(key: object) -> Key:
    """Parse a concrete EBRL key into named fields; raise ValueError for anything else.

    ``parse("ebrl/live/r/sim/3").service == "sim"``; ``parse("ebrl/data/r/obs/2").group == 2``."""
    text = str(key)
    chunks = text.split("/")
    if len(chunks) < 4 or chunks[0] != ROOT or chunks[1] not in CATEGORIES:
        raise ValueError(f"not an EBRL key: {text!r}")
    category, run, rest = chunks[1], chunks[2], chunks[3:]
    if category == "data":
        grouped = rest[0] in ("obs", "act", "traj") and (len(rest) == 2 or rest[0] == "traj" and rest[2:] == ["packed"])
        group = int(rest[1]) if grouped and rest[1].isdigit() else None
        return Key(category, run, kind=rest[0], group=group)
    if category == "stats" and rest[0] in RESERVED_STATS:
        return Key(category, run, service=rest[0], lane="/".join(rest[1:]))
    if len(rest) < 2:
        raise ValueError(f"not an EBRL key: {text!r} (no instance)")
    return Key(category, run, service=rest[0], instance=rest[1], kind=rest[2] if category == "ctl" and len(rest) > 2 else "")


def role_of(key: object) -> str:
    """The service role a liveliness/stats/control key is about (``""`` for keys that name none)."""
    try:
        return parse(key).service
    except ValueError:
        return ""
