"""The service graph (issue 37): ebrl/graph.py declares what each role publishes, subscribes to, queries and
answers; a real run of sim, gen, train, eval and log on the in-memory bus uses nothing else, and docs/graph.md
is generated from the declaration."""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest

from ebrl import graph
from ebrl.bus import keys
from ebrl.bus.memory import MemoryBus, MemoryNetwork
from ebrl.messages import StatsReport
from test_pipeline import service_class, small_config

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


def test_every_key_a_service_uses_in_a_run_is_declared_by_its_role(tmp_path):
    cfg = small_config(tmp_path, eval={"every": 1, "episodes": 1, "video_episodes": 0})
    roles = ("train", "gen", "sim", "eval", "log")
    used = {role: set() for role in roles}

    async def main():
        network = MemoryNetwork()
        watch = MemoryBus(network)
        services = [service_class(role)(cfg, 0, run_dir=str(tmp_path)) for role in roles]
        tasks = [asyncio.create_task(s.main(bus=RecordingBus(network, used[s.role]), signals=False))
                 for s in services]
        seen = watch.subscribe(keys.stats("pipe", "gen", 0), StatsReport)
        try:
            while True:  # until generation acts with version 2: every stage has published and received
                reports = [r for _, r in seen.drain()]
                if any(r.metrics.get("gen/policy_version", 0) >= 2 for r in reports):
                    break
                await asyncio.sleep(0.05)
        finally:
            for service in services:
                if service.stopping is not None:
                    service.request_stop("test over")
            await asyncio.wait_for(asyncio.gather(*tasks, return_exceptions=True), 60)
            await watch.close()

    asyncio.run(asyncio.wait_for(main(), 180))
    undeclared = {role: sorted(k for k in keys_ if not graph.allowed(role, 0, k[0], k[1], "pipe"))
                  for role, keys_ in used.items()}
    assert not any(undeclared.values()), f"keys used but not declared in ebrl/graph.py: {undeclared}"
    # and the run did use the data flows the graph draws
    assert ("put", keys.obs("pipe", 0)) in used["sim"] and ("put", keys.weights("pipe")) in used["train"]
    assert ("sub", keys.obs("pipe")) in used["gen"] and ("answer", keys.weights_all("pipe")) in used["train"]


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
