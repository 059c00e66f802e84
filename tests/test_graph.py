"""The service graph (issue 37): ebrl/graph.py declares what each role publishes, subscribes to, queries and
answers, and docs/graph.md is generated from the declaration. :class:`RecordingBus` notes what a service really
uses; tests/test_in_process.py runs every kind of service on it and checks it used nothing undeclared."""

from __future__ import annotations

from pathlib import Path

import pytest

from ebrl import graph
from ebrl.bus.memory import MemoryBus, MemoryNetwork

ROOT = Path(__file__).resolve().parent.parent


class RecordingBus(MemoryBus):
    """A service's in-memory bus that notes every key it touches, by direction (the graph's words)."""

    def __init__(self, network: MemoryNetwork, used: set[tuple[str, str]]):
        super().__init__(network)
        self.used = used

    def _put(self, key, payload, express):
        self.used.add(("put", key))
        super()._put(key, payload, express)

    def _feed(self, key, callback):
        self.used.add(("sub", key))
        return super()._feed(key, callback)

    def declare_token(self, key):
        self.used.add(("token", key))
        return super().declare_token(key)

    def watch_liveliness(self, key, on_change):
        self.used.add(("watch", key))
        return super().watch_liveliness(key, on_change)

    def declare_queryable_raw(self, key, on_query):
        self.used.add(("answer", key))
        return super().declare_queryable_raw(key, on_query)

    async def get_raw(self, selector, on_reply, payload=None, timeout=1.0):
        self.used.add(("query", selector.split("?", 1)[0]))
        return await super().get_raw(selector, on_reply, payload, timeout)


def recording(used: dict[str, set[tuple[str, str]]]):
    """``InProcessRun``'s ``make_bus``: each service's bus notes what it touches in ``used[role]``."""
    return lambda network, role: RecordingBus(network, used.setdefault(role, set()))


def undeclared(used: dict[str, set[tuple[str, str]]], run: str = "pipe") -> dict[str, list[tuple[str, str]]]:
    return {role: sorted(k for k in keys_ if not graph.allowed(role, 0, k[0], k[1], run))
            for role, keys_ in used.items() if any(not graph.allowed(role, 0, d, k, run) for d, k in keys_)}


@pytest.mark.parametrize("role, direction, key, ok", [
    ("gen", "put", "ebrl/data/pipe/act/3", True),
    ("gen", "put", "ebrl/data/pipe/traj/3", False),  # only sim publishes segments
    ("sim", "put", "ebrl/data/pipe/weights", False),  # only train publishes weights
    ("alloc", "put", "ebrl/ctl/pipe/gen/0/quota", True),
    ("alloc", "put", "ebrl/ctl/pipe/gen/0/stop", False),  # stopping a run is the launcher's
    ("sim", "put", "ebrl/stats/pipe/sim/0", True),
    ("sim", "put", "ebrl/stats/pipe/train/0", False),  # a service reports as itself only
    ("train", "sub", "ebrl/ctl/pipe/train/0/*", True),
    ("train", "sub", "ebrl/ctl/pipe/gen/0/*", False),
])
def test_a_role_is_allowed_only_what_it_declares(role, direction, key, ok):
    assert graph.allowed(role, 0, direction, key, "pipe") is ok


def test_key_expressions_intersect_as_zenoh_matches_them():
    assert graph.intersects("ebrl/data/r/obs/*", "ebrl/data/r/**")
    assert graph.intersects("ebrl/ctl/r/*/*/quota", "ebrl/ctl/r/gen/0/*")
    assert not graph.intersects("ebrl/ctl/r/sim/*/quota", "ebrl/ctl/r/gen/0/*")
    assert graph.covers("ebrl/stats/r/**", "ebrl/stats/r/events/sim")
    assert not graph.covers("ebrl/stats/r/*/*", "ebrl/stats/r/a/b/c")


def test_docs_graph_md_is_generated_from_the_declaration():
    assert (ROOT / "docs" / "graph.md").read_text() == graph.markdown(), \
        "docs/graph.md is stale: python -m ebrl.cli graph --markdown > docs/graph.md"
