"""The service graph (issue 37): ebrl/graph.py declares what each role publishes, subscribes to, queries and
answers, and docs/graph.md is generated from the declaration. :class:`RecordingBus` notes what a service really
uses; tests/test_in_process.py runs every kind of service on it and checks it used nothing undeclared."""

from __future__ import annotations

from pathlib import Path

import pytest

from ebrl import graph, keys
from ebrl.bus.memory import MemoryBus, MemoryNetwork

ROOT = Path(__file__).resolve().parent.parent


class RecordingBus(MemoryBus):
    """A service's in-memory bus that notes every key it touches, by direction (the graph's words)."""

    def __init__(self, network: MemoryNetwork, used: set[tuple[str, str]]):
        super().__init__(network)
        self.used = used

    def _put(self, key, payload, express, msg=None):
        self.used.add(("put", key))
        super()._put(key, payload, express, msg)

    def _feed(self, key, callback, subscription=None):
        self.used.add(("sub", key))
        return super()._feed(key, callback, subscription)

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


def test_the_generated_access_rules_let_each_role_send_only_what_it_declares(tmp_path):
    """graph.access_control on a real Zenoh router that knows every client's identity (user names and passwords
    in its dictionary): sim's weights are dropped where they enter, train's arrive; sim's observations arrive,
    train's are dropped. Each sender's refused message goes first on its link, so once the allowed one after
    it arrived, the refused one had its chance."""
    import json
    import secrets
    import time

    import zenoh

    from ebrl.bus.endpoints import free_port

    roles = ("launcher", "sim", "gen", "train")
    passwords = {role: secrets.token_hex(16) for role in roles}
    users = tmp_path / "users"
    users.write_text("".join(f"{graph.username(r)}:{passwords[r]}\n" for r in roles))
    endpoint = f"tcp/127.0.0.1:{free_port()}"

    def config(role: str) -> zenoh.Config:
        conf = zenoh.Config()
        router = role == "launcher"
        settings = {"mode": "router" if router else "client", "scouting/multicast/enabled": False,
                    "listen/endpoints": [endpoint] if router else [], "connect/endpoints": [] if router else [endpoint],
                    "transport/auth/usrpwd": {"user": graph.username(role), "password": passwords[role],
                                              **({"dictionary_file": str(users)} if router else {})}}
        if router:
            settings["access_control"] = graph.access_control("r")
        for path, value in settings.items():
            conf.insert_json5(path, json.dumps(value))
        return conf

    got: list[tuple[str, bytes]] = []
    sessions = [zenoh.open(config(role)) for role in roles]
    try:
        _, sim, gen, train = sessions
        for key in ("ebrl/data/r/weights", "ebrl/data/r/obs/*"):
            gen.declare_subscriber(key, lambda s: got.append((str(s.key_expr), s.payload.to_bytes())))
        deadline = time.monotonic() + 30
        while not {b"sim obs", b"train weights"} <= {payload for _, payload in got}:
            assert time.monotonic() < deadline, f"the allowed messages never arrived: {got}"
            sim.put("ebrl/data/r/weights", b"sim weights")  # refused
            sim.put("ebrl/data/r/obs/0", b"sim obs")
            train.put("ebrl/data/r/obs/0", b"train obs")  # refused
            train.put("ebrl/data/r/weights", b"train weights")
            time.sleep(0.05)
    finally:
        for session in sessions:
            session.close()
    assert {payload for _, payload in got} == {b"sim obs", b"train weights"}, got


def test_a_roles_builders_make_the_keys_of_its_declared_flows_and_refuse_any_other():
    """Code gets its keys from ``graph.keys_of`` (tests/test_architecture.py checks no module builds one itself):
    the same keys ebrl.keys builds, for the flows the role declares in that direction alone."""
    sim, gen, alloc = graph.keys_of("pipe", "sim", 1), graph.keys_of("pipe", "gen"), graph.keys_of("pipe", "alloc")
    assert sim.put("obs", group=3) == keys.obs("pipe", 3) and sim.sub("act", group=3) == keys.act("pipe", 3)
    assert sim.put("stats") == keys.stats("pipe", "sim", 1) and sim.token() == keys.live("pipe", "sim", 1)
    assert sim.sub("ctl", kind="quota") == keys.ctl("pipe", "sim", 1, "quota") and sim.watch() == keys.live_all("pipe")
    assert gen.sub("obs") == keys.obs("pipe") and gen.query("weights") == keys.weights_all("pipe")
    assert alloc.put("quota", service="gen", instance=0) == keys.ctl("pipe", "gen", 0, "quota")
    assert graph.keys_of("pipe", "launcher", 2).put("stop", service="sim", instance=0) == \
        keys.ctl("pipe", "sim", 0, "stop")
    with pytest.raises(ValueError, match="sim declares no flow 'weights' it publishes"):
        sim.put("weights")  # only train publishes weights
    with pytest.raises(ValueError, match="gen declares no flow 'obs' it publishes"):
        gen.put("obs", group=0)  # gen subscribes to observations
    with pytest.raises(ValueError, match="outside its flow 'stats'"):
        sim.put("stats", instance=2)  # a service reports as itself only
    with pytest.raises(ValueError, match="outside its flow 'quota'"):
        alloc.put("quota", service="log", instance=0)  # the allocator plans sim, gen and train alone
    with pytest.raises(ValueError, match="declares no flow 'stop'"):
        alloc.put("stop", service="gen", instance=0)  # stopping a run is the launcher's
    with pytest.raises(ValueError, match="no role 'nobody'"):
        graph.keys_of("pipe", "nobody")
    # an observer reads one run, or every run (None)
    assert graph.keys_of("pipe", "observer").sub("stats") == keys.stats_all("pipe")
    assert graph.keys_of(None, "observer").sub("stats") == "ebrl/stats/**" == keys.stats()
    assert graph.keys_of(None, "observer").watch() == keys.live("*", "launcher", "*")
    with pytest.raises(ValueError, match="needs the run's name"):
        graph.keys_of(None, "sim").put("obs", group=0)


def test_every_flow_builds_its_own_pattern():
    for role in graph.FLOWS:
        run = None if role == "observer" else "pipe"
        for flow in graph.flows(role):
            pattern = flow.pattern.replace(graph.R, "pipe").replace(graph.ROLE, role).replace(graph.I, "0")
            assert flow.build(run, role, 0, {}) == pattern, (role, flow.name)


def test_a_role_is_one_record_the_config_the_launcher_and_the_metrics_read():
    """Start order (ebrl.config.ROLES), module (what the launcher runs), service or not, metrics namespace:
    each service's are on its record in ebrl/graph.py."""
    from ebrl import config
    from ebrl.metrics import CATALOG
    from ebrl.metrics import NAMESPACES

    assert config.ROLES == ("viz", "log", "replay", "train", "gen", "sim", "eval", "alloc")
    assert set(graph.SERVICES) == set(config.ROLES) and "launcher" not in graph.SERVICES
    for name, role in graph.ROLES.items():
        assert not role.service or (ROOT / (role.module.replace(".", "/") + ".py")).is_file(), name
        assert not role.stats or any(m.name.startswith(role.stats + "/") for m in CATALOG), name
    assert set(NAMESPACES) == {r.stats for r in graph.ROLES.values() if r.stats}
