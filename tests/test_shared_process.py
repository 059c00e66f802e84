"""Services that share a process (``run.processes``, issue 51): planned per host, started as one process over one
bus session, each service still itself on the bus (its stats, lanes, token), restarted together, and no more
rights for the process than its services have."""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import time

import psutil
import pytest
import zenoh

from ebrl import config, graph
from ebrl import keys
from ebrl.bus import auth
from ebrl.bus.session import BusOptions, zenoh_config
from ebrl.hosts import decide_processes, plan
from ebrl.testing import StatsWatcher
from ebrl.viz import record
from helpers import ROOT, free_port, up

SHARED = 'run.processes=[["sim", "gen", "train"]]'


def load(**sections) -> config.Config:
    return config.from_dict({"viz": {"rerun": "off"}, "log": {"tensorboard": False, "csv": False}, **sections})


# --- the plan ----------------------------------------------------------------------------------------------------


def test_a_host_starts_each_group_as_one_process_where_its_first_service_starts():
    cfg, here = plan(load(run={"processes": [["sim", "gen", "train"]]}, alloc={"enabled": True}))
    assert here.processes(cfg) == [(("train", 0), ("gen", 0), ("sim", 0)), (("alloc", 0),)]
    cfg, here = plan(load(run={"processes": [["gen", "sim"]]}))
    assert here.processes(cfg) == [(("train", 0),), (("gen", 0), ("sim", 0))]
    cfg, here = plan(load())
    assert here.processes(cfg) == [(("train", 0),), (("gen", 0),), (("sim", 0),)]
    cfg, here = plan(load(run={"processes": [["sim", "viz"]]}))  # viz is off: sim alone
    assert here.processes(cfg) == [(("train", 0),), (("gen", 0),), (("sim", 0),)]


def test_a_sim_host_shares_its_group_only_when_the_whole_group_runs_there():
    hosts = {"learner": {"services": ["gen", "train"], "listen": ["tcp/127.1.0.1:7447"]},
             "sims": {"services": ["sim"], "connect": ["tcp/127.1.0.1:7447"]}}
    cfg = load(hosts=hosts, run={"processes": [["gen", "train"]]})
    learner_cfg, learner = plan(cfg, host="learner")
    assert learner.processes(learner_cfg) == [(("train", 0), ("gen", 0))]
    with pytest.raises(config.ConfigError, match=r"run.processes: \['sim', 'gen'\] is split between hosts"):
        split_cfg, sims = plan(load(hosts=hosts, run={"processes": [["sim", "gen"]]}), host="sims")
        sims.processes(split_cfg)


@pytest.mark.parametrize("processes, message", [
    ([["sim"]], "at least two services"),
    ([["sim", "simulator"]], "unknown service 'simulator'"),
    ([["sim", "gen"], ["gen", "train"]], "gen is named twice"),
])
def test_a_wrong_placement_names_the_problem(processes, message):
    with pytest.raises(config.ConfigError, match=message):
        load(run={"processes": processes})


def test_training_ranks_never_share_a_process():
    with pytest.raises(config.ConfigError, match="each training rank runs in a process of its own"):
        load(run={"processes": [["gen", "train"]]}, train={"world_size": 2, "batch_size": 2048})


def test_auto_shares_a_process_only_for_a_gpu_simulator_ebrl_ships_with_every_stage_on_a_gpu_host():
    mjwarp = config.load(str(ROOT / "configs" / "mjwarp_pickcube.toml"), ['viz.rerun="off"'])
    assert mjwarp.run.processes == "auto"  # the default
    cfg, here = plan(mjwarp)
    shared, line = decide_processes(cfg, here, gpu=True)
    assert shared.run.processes == [["sim", "gen", "train"]] and "one GPU" in line
    assert (("train", 0), ("gen", 0), ("sim", 0)) in here.processes(shared)
    cases = {"the vectorized groups keep their processes": (mjwarp, {}, False),  # no GPU on this host
             "steps on the CPU": (load(), {}, True),  # the quickstart's gymnasium env
             "is your own code": (mjwarp, {"env": {"id": "mytasks:Pick-v0"}}, True),
             "not every stage on this host": (mjwarp, {"only": "sim"}, True)}
    for why, (base, change, gpu) in cases.items():
        only = change.pop("only", None)
        changed = config.from_dict({**base.to_dict(), **{k: {**base.to_dict()[k], **v} for k, v in change.items()}})
        cfg, here = plan(changed, only=only)
        kept, line = decide_processes(cfg, here, gpu)
        assert kept.run.processes == [] and why in line, (why, line)
    cfg, here = plan(mjwarp)  # a GPU simulator with the allocator (none of EBRL's can have one today)
    with_alloc = dataclasses.replace(cfg, alloc=dataclasses.replace(cfg.alloc, enabled=True))
    assert decide_processes(with_alloc, here, gpu=True)[0].run.processes == []
    explicit = config.from_dict({**mjwarp.to_dict(), "run": {**mjwarp.to_dict()["run"], "processes": []}})
    assert decide_processes(*plan(explicit), gpu=True) == (explicit, "")  # a user's choice is kept, unsaid


def test_auto_shares_sim_and_gen_on_a_cpu_host_for_the_ebrl_mode_with_env_workers():
    cfg, here = plan(load())  # the quickstart's gymnasium env, one worker process per env
    shared, line = decide_processes(cfg, here, gpu=False)
    assert shared.run.processes == [["sim", "gen"]] and "no GPU on this host" in line, line
    assert here.processes(shared) == [(("train", 0),), (("gen", 0), ("sim", 0))]  # training keeps its own
    cases = {"keeps its own layout": {"run": {"mode": "colocated"}},  # a baseline models its layout
             "is your own code": {"env": {"id": "mytasks:Pick-v0"}},
             "the vectorized groups keep their processes": {"sim": {"vectorized": True}},
             "per process": {"alloc": {"enabled": True}},
             "not every stage on this host": {"only": "gen"}}
    for why, change in cases.items():
        only = change.pop("only", None)
        cfg, here = plan(load(**change), only=only)
        kept, line = decide_processes(cfg, here, gpu=False)
        assert kept.run.processes == [] and why in line, (why, line)
    sac = load(algo={"name": "sac"}, policy={"kind": "squashed"})  # the replay joins training, beside sim and gen
    cfg, here = plan(sac)
    assert decide_processes(cfg, here, gpu=False)[0].run.processes == [["sim", "gen"], ["train", "replay"]]
    cfg, here = plan(load(algo={"name": "sac"}, policy={"kind": "squashed"}, run={"mode": "colocated"}))
    assert decide_processes(cfg, here, gpu=False)[0].run.processes == [["train", "replay"]]


# --- rights --------------------------------------------------------------------------------------------------------


def test_a_shared_process_may_send_what_its_services_may_and_nothing_more(tmp_path):
    """Against a real router as a client-mode launcher makes it for a process of gen and sim (gen/0 signs in for
    it): the process's session publishes gen's and sim's reports and sim's observations, and holds both tokens;
    weights, training's reports and another host's simulator token it sends are dropped where they enter."""
    secret = auth.create(tmp_path / "bus.secret")
    processes = [(("train", 0),), (("gen", 0), ("sim", 0))]
    leads = tuple(unit[0] for unit in processes)
    dictionary = auth.write_router_dictionary(secret, tmp_path / "bus.router-0.secret", leads)
    assert "ebrl-sim-0:" not in dictionary.read_text()  # sim/0 has no line of its own: gen/0 signs in for it
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    planned = (("train", 0), ("gen", 0), ("sim", 0), ("launcher", 0))
    launcher = zenoh.open(zenoh_config(BusOptions(
        mode="router", listen=[endpoint], secret_file=str(secret), role="launcher", run="r", instances=leads,
        dictionary_file=str(dictionary), groups=1, planned=planned, shares=(processes[1],))))
    shared = zenoh.open(zenoh_config(BusOptions(mode="client", connect=[endpoint], listen=[], role="gen",
                                                identity=auth.instance_line(secret, "gen", 0))))
    try:
        got: set[str] = set()
        live: set[str] = set()
        launcher.declare_subscriber("ebrl/**", lambda s: got.add(str(s.key_expr)))
        launcher.liveliness().declare_subscriber("ebrl/live/**", lambda s: live.add(str(s.key_expr)), history=True)
        tokens = [shared.liveliness().declare_token(keys.live("r", role, 0)) for role in ("train", "gen", "sim")]
        refused = [keys.weights("r"), keys.stats("r", "train", 0), keys.obs("r", 1)]
        allowed = [keys.stats("r", "gen", 0), keys.stats("r", "sim", 0), keys.obs("r", 0), keys.act("r", 0)]
        deadline = time.monotonic() + 60  # a bound for a hang, not a timing window
        while not set(allowed) <= got or len(live) < 2:
            for key in refused + allowed:  # refused first: on one link, in order
                shared.put(key, b"x")
            assert time.monotonic() < deadline, (sorted(got), sorted(live))
            time.sleep(0.05)
        assert not set(refused) & got, sorted(set(refused) & got)
        assert live == {keys.live("r", "gen", 0), keys.live("r", "sim", 0)}, sorted(live)  # not train's
        del tokens
    finally:
        shared.close()
        launcher.close()
    acl = graph.access_control("r", instances=leads, planned=planned, shares=(processes[1],))
    policy = next(p for p in acl["policies"] if p["id"] == "gen-0")
    assert {"gen-0-put", "sim-0-put", "gen-0-impersonate"} <= set(policy["rules"])
    assert not [p for p in acl["policies"] if p["id"] == "sim-0"]  # no identity of its own


# --- a live run ------------------------------------------------------------------------------------------------------


def shared_process(run) -> psutil.Process:
    """The launcher's child running ``ebrl.process`` (the shared one)."""
    for child in psutil.Process(run.proc.pid).children():
        if "ebrl.process" in child.cmdline():
            return child
    raise AssertionError("no shared process among the launcher's children")


@pytest.mark.slow  # 35 s: the fast suite keeps to its 10 minutes on 2 cores
def test_services_sharing_a_process_train_report_as_themselves_and_restart_together(tmp_path):
    """The quickstart with sim, gen and train in one process: one child process for the three; a user's stats
    subscriber sees each service's own reports and Gantt lanes as from three processes, while observations, actions
    and segments go by reference between them; a kill -9 of the process
    is noticed, it is started again with all three, and the run finishes every iteration."""
    with up(tmp_path, "configs/quickstart.toml", "run.iterations=16", 'viz.rerun="off"', SHARED,
            name="shared") as run:
        line = run.wait_for_line("all services live", 300)
        assert "train/0+gen/0+sim/0" in line
        with StatsWatcher(run) as stats:
            stats.wait_for(lambda: (stats.latest("train/0", "train/policy_version") or 0) >= 4, 300, "4 updates")
            victim = shared_process(run)
            assert [c for c in psutil.Process(run.proc.pid).children() if "ebrl.services.sim" in c.cmdline()] == []
            os.kill(victim.pid, signal.SIGKILL)
            code = run.wait(400)
    assert code == 0, run.output[-4000:]
    summary = json.loads((run.run_dir / "summary.json").read_text())
    assert summary["iterations"] == 16 and summary["restarts"] == {"train/0+gen/0+sim/0": 1}, summary
    assert "train/0+gen/0+sim/0 exited with status -9" in run.output
    for source, metric in (("sim/0", "sim/env_steps"), ("gen/0", "gen/batches"), ("train/0", "train/updates")):
        assert stats.reports(source) and stats.latest(source, metric) is not None, (source, metric)
    # observations, actions and segments went by reference in the process (ebrl.bus.local), nothing refused
    for source in ("sim/0", "gen/0"):
        assert stats.latest(source, "bus/local") > 0 and stats.latest(source, "bus/refused") == 0, source
    assert {"sim.g0", "gen", "train", "weights"} <= set(record.read(run.run_dir).lanes)  # a process's own each
    assert (run.run_dir / "logs" / "train-0+gen-0+sim-0.log").exists()
