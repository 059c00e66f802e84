"""Scale-out: which services a host starts ([hosts], --only), runs over several hosts (loopback ports, and
real network namespaces joined by veth links), and the router."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
import uuid

import pytest

import helpers
from netns_hosts import (Namespaces, hosts_sets, namespaces_unavailable, ranks_across_hosts_config,
                         shared_secret, tls_files, tls_hosts_config)
from ebrl import config
from ebrl.hosts import plan, planned_instances

ROOT = helpers.ROOT
QUICK = str(ROOT / "configs" / "quickstart.toml")

HOSTS = {
    "learner": {"services": ["gen", "train"], "listen": ["tcp/127.1.0.1:7447"]},
    "sim-a": {"services": ["sim"], "connect": ["tcp/127.1.0.1:7447"], "cores": [0]},
    "sim-b": {"services": ["sim"], "connect": ["tcp/127.1.0.1:7447"]},
}


def load(**sections) -> config.Config:
    """A config without the optional services (viz, the log service's sinks) unless ``sections`` turn them on."""
    return config.from_dict({"viz": {"rerun": "off"}, "log": {"tensorboard": False, "csv": False}, **sections})


# --- planning -------------------------------------------------------------------------------------------


def test_a_hosts_table_places_services_and_numbers_hosts():
    cfg = load(hosts=HOSTS)
    learner_cfg, learner = plan(cfg, host="learner")
    assert learner.roles == ("train", "gen") and learner.instance == 0 and learner.multi and learner.primary
    assert learner_cfg.bus.listen == ["tcp/127.1.0.1:7447"]
    sim_cfg, sim = plan(cfg, host="sim-a")
    assert sim.roles == ("sim",) and sim.instance == 1 and not sim.primary
    assert sim_cfg.bus.connect == ["tcp/127.1.0.1:7447"] and sim_cfg.sim.cores == [0]
    assert plan(cfg, host="sim-b")[1].instance == 2


def test_the_run_s_planned_instances_are_every_host_s_with_its_launcher():
    cfg = load(hosts=HOSTS, alloc={"enabled": True})
    learner_cfg, learner = plan(cfg, host="learner")
    assert planned_instances(learner_cfg, learner) == (("train", 0), ("gen", 0), ("alloc", 0), ("launcher", 0),
                                                       ("sim", 1), ("launcher", 1), ("sim", 2), ("launcher", 2))
    assert planned_instances(*plan(cfg, host="sim-b")) == planned_instances(learner_cfg, learner)  # the same on each
    one_cfg, one = plan(load(train={"world_size": 2}))
    assert planned_instances(one_cfg, one) == (("train", 0), ("train", 1), ("gen", 0), ("sim", 0), ("launcher", 0))
    assert planned_instances(*plan(load(), only="sim", instance=3)) is None  # hosts that join by --only


def test_the_allocator_goes_with_train_and_plans_that_hosts_cores():
    cfg = load(hosts=HOSTS, alloc={"enabled": True})
    assert plan(cfg, host="learner")[1].roles == ("train", "gen", "alloc")
    assert plan(cfg, host="sim-a")[1].roles == ("sim",)
    assert list(plan(cfg, host="learner")[1].instances("alloc", cfg)) == [0]
    hosts = {**HOSTS, "sim-b": {**HOSTS["sim-b"], "services": ["sim", "alloc"]}}
    with pytest.raises(config.ConfigError, match=r"\[hosts.sim-b\]: the allocator .alloc. runs on the host that"):
        plan(load(hosts=hosts, alloc={"enabled": True}), host="sim-b")


def test_viz_goes_with_train_unless_a_host_names_it():
    cfg = load(hosts=HOSTS, viz={"rerun": "save"})
    assert plan(cfg, host="learner")[1].roles == ("viz", "train", "gen")
    hosts = {**HOSTS, "sim-b": {**HOSTS["sim-b"], "services": ["sim", "viz"]}}
    cfg = load(hosts=hosts, viz={"rerun": "save"})
    assert plan(cfg, host="learner")[1].roles == ("train", "gen")
    assert plan(cfg, host="sim-b")[1].roles == ("viz", "sim")


def test_the_log_service_goes_with_train_unless_a_host_names_it_and_is_off_without_sinks():
    tracked = {"tensorboard": True}
    cfg = load(hosts=HOSTS, log=tracked)
    assert plan(cfg, host="learner")[1].roles == ("log", "train", "gen")
    assert plan(cfg, host="sim-a")[1].roles == ("sim",)
    hosts = {**HOSTS, "sim-b": {**HOSTS["sim-b"], "services": ["sim", "log"]}}
    assert plan(load(hosts=hosts, log=tracked), host="learner")[1].roles == ("train", "gen")
    assert plan(load(hosts=hosts, log=tracked), host="sim-b")[1].roles == ("log", "sim")
    assert plan(load(log=tracked))[1].roles == ("log", "train", "gen", "sim")
    assert plan(load(log=tracked), only="gen,train")[1].roles == ("log", "train", "gen")
    assert plan(load(log=tracked), only="sim", instance=1)[1].roles == ("sim",)
    assert plan(config.from_dict({}))[1].roles == ("log", "train", "gen", "sim")  # tensorboard and csv by default
    assert "log" not in plan(load(log={"tensorboard": False, "csv": False, "wandb": False}))[1].roles


@pytest.mark.parametrize("hosts, message", [
    ({"a": {"services": ["sim", "gen"]}}, "a host must run train"),
    ({"a": {"services": ["sim", "gen", "train"]}, "b": {"services": ["train"]}},  # two hosts, one rank
     "the hosts that run train hold a: 0, b: 0 ranks"),
    ({"a": {"services": ["sim", "gen", "train"]}, "b": {"services": ["gen"]}}, "exactly one host must run gen"),
    ({"a": {"services": ["sim", "gen", "train"]}, "b": {"services": ["sim"], "ranks": 2}},
     "hosts.b.ranks = 2: training ranks on a host that runs train"),
    ({"a": {"services": ["gen", "train", "simm"]}}, "unknown service 'simm'"),
    ({"a": {"services": ["gen", "train"], "cpus": [1]}}, "unknown key hosts.a.cpus"),
    ({"A!": {"services": ["gen", "train", "sim"]}}, "host name"),
    ({"a": {"services": ["gen", "train"]}}, "no host runs sim"),
])
def test_a_wrong_hosts_table_names_the_problem(hosts, message):
    with pytest.raises(config.ConfigError, match=message):
        load(hosts=hosts)


TRAIN_HOSTS = {"learner": {"services": ["gen", "train"]}, "b": {"services": ["train", "sim"], "ranks": 3}}


def test_training_ranks_on_several_hosts_are_numbered_across_them_and_need_a_trusted_rendezvous():
    from ebrl import ranknet

    trusted = {"world_size": 4, "rendezvous": "10.0.0.1:29500", "trusted_networks": ["10.0.0.0/24"]}
    cfg = load(hosts=TRAIN_HOSTS, train=trusted, log={"csv": True})
    assert config.train_ranks(cfg) == {"learner": range(0, 1), "b": range(1, 4)}
    learner_cfg, learner = plan(cfg, host="learner")
    b_cfg, b = plan(cfg, host="b")
    assert learner.primary and not b.primary and b.ranks_elsewhere and b.instances("train", cfg) == range(1, 4)
    assert "log" in learner.roles and "log" not in b.roles  # what goes with train goes with rank 0
    assert ("train", 3) in planned_instances(cfg, learner)
    here = {"lo": ["127.0.0.1"], "eth1": ["10.0.0.1"]}
    assert ranknet.across_hosts(cfg, learner, here) == ("10.0.0.1:29500", "eth1")
    assert ranknet.across_hosts(cfg, b, {"lo": ["127.0.0.1"], "ib0": ["10.0.0.7"]}) == ("10.0.0.1:29500", "ib0")
    with pytest.raises(ValueError, match=r"none of its addresses is in train.trusted_networks \(10.0.0.0/24\): lo: "
                                         r"127.0.0.1; eth0: 192.168.1.5"):
        ranknet.across_hosts(cfg, b, {"lo": ["127.0.0.1"], "eth0": ["192.168.1.5"]})
    with pytest.raises(ValueError, match="10.0.0.1 is not an address of this host, the primary"):
        ranknet.across_hosts(cfg, learner, {"eth1": ["10.0.0.2"]})
    outside = load(hosts=TRAIN_HOSTS, train={**trusted, "trusted_networks": ["10.1.0.0/16"]})
    with pytest.raises(ValueError, match=r"is outside train.trusted_networks \(10.1.0.0/16\): the ranks' channel has "
                                         "no authentication"):
        ranknet.across_hosts(outside, plan(outside, host="learner")[1], here)
    for train, message in [({**trusted, "rendezvous": ""}, "needs HOST:PORT on the primary host"),
                           ({**trusted, "trusted_networks": []}, "name the networks"),
                           ({**trusted, "world_size": 3}, "learner: 0, b: 3 ranks"),
                           ({**trusted, "trusted_networks": ["10.0.0.0/33"]}, "train.trusted_networks: ")]:
        with pytest.raises(config.ConfigError, match=message):
            load(hosts=TRAIN_HOSTS, train=train)


def test_only_and_instance():
    cfg = load()
    assert plan(cfg)[1].roles == ("train", "gen", "sim") and not plan(cfg)[1].multi
    _, sim = plan(cfg, only="sim", instance=3)
    assert sim.roles == ("sim",) and sim.instance == 3 and sim.multi
    assert plan(cfg, only="sim,train,gen")[1].roles == ("train", "gen", "sim")  # start order, not typed order
    with pytest.raises(config.ConfigError, match="unknown service 'gem'"):
        plan(cfg, only="sim,gem")
    with pytest.raises(config.ConfigError, match=r"alloc is off in this config \(alloc: alloc.enabled\)"):
        plan(cfg, only="alloc")
    with pytest.raises(config.ConfigError, match=r"eval: eval.every > 0; viz: viz.rerun not off\)"):
        plan(cfg, only="eval,viz")
    watched = load(viz={"rerun": "save"})
    assert plan(watched, only="gen,train")[1].roles == ("viz", "train", "gen")  # viz goes with train
    assert plan(watched, only="sim", instance=1)[1].roles == ("sim",)
    allocating = load(alloc={"enabled": True})
    assert plan(allocating, only="sim", instance=1)[1].roles == ("sim",)
    assert plan(allocating, only="gen,train")[1].roles == ("train", "gen", "alloc")  # the allocator goes with train
    with pytest.raises(config.ConfigError, match="the allocator .alloc. runs on the host that trains"):
        plan(allocating, only="sim,alloc")
    with pytest.raises(config.ConfigError, match="use it with --only"):
        plan(cfg, instance=1)
    with pytest.raises(config.ConfigError, match="start each host with --host"):
        plan(load(hosts=HOSTS))
    with pytest.raises(config.ConfigError, match=r"no \[hosts.nope\]"):
        plan(load(hosts=HOSTS), host="nope")


def test_the_resolved_config_keeps_its_hosts_table():
    cfg = load(hosts=HOSTS)
    path = ROOT / "runs" / f"hosts-{uuid.uuid4().hex}.toml"
    path.parent.mkdir(exist_ok=True)
    try:
        path.write_text(config.dump_toml(cfg))
        again = config.load(str(path))
    finally:
        path.unlink()
    assert again.hosts == cfg.hosts


def test_a_host_that_joins_another_takes_a_free_port_and_the_one_others_join_does_not():
    """Two launchers on one machine: the second, which connects to the first, listens only for its own services
    and takes a free port where its configured one is busy; the primary's port is the one others connect to,
    so a busy one is an error (issue 54)."""
    import socket

    from ebrl.launch import fixed_listen, launcher_endpoint

    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        listen = f'bus.listen=["tcp/127.0.0.1:{port}"]'
        joining_cfg, joining = plan(config.load(QUICK, [listen, 'bus.connect=["tls/192.0.2.1:7447"]']), only="sim",
                                    instance=1)
        assert not fixed_listen(joining_cfg, joining)
        endpoint = launcher_endpoint(joining_cfg, joining)
        assert endpoint.startswith("tcp/127.0.0.1:") and endpoint != f"tcp/127.0.0.1:{port}"
        primary_cfg, primary = plan(config.load(QUICK, [listen]), only="gen,train")
        assert fixed_listen(primary_cfg, primary)
        with pytest.raises(OSError, match="the port is busy or the address is not this host's"):
            launcher_endpoint(primary_cfg, primary)


def test_a_launcher_listening_beyond_the_host_gives_its_services_a_loopback_endpoint(tmp_path):
    """The learner listens on a TLS address for the other hosts; its own services and scripts reach it over a
    loopback TCP port it listens on as well, even where bus.config_file names its listen endpoints (issue 54)."""
    from ebrl.bus.session import BusOptions, zenoh_config
    from ebrl.launch import local_endpoint

    assert local_endpoint("tcp/127.0.0.1:7447") == "tcp/127.0.0.1:7447" and local_endpoint("") == ""
    local = local_endpoint("tls/192.0.2.1:7447")
    assert local.startswith("tcp/127.0.0.1:")
    (tmp_path / "z.json5").write_text('{ listen: { endpoints: ["tls/192.0.2.1:7447"] } }')
    for file in ("", str(tmp_path / "z.json5")):
        conf = zenoh_config(BusOptions(mode="router", listen=["tls/192.0.2.1:7447"], config_file=file,
                                       file_listen_wins=True, local=local))
        assert json.loads(conf.get_json("listen/endpoints")) == ["tls/192.0.2.1:7447", local]


def test_ebrl_up_with_a_bad_only_exits_2_and_starts_nothing(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "ebrl.cli", "up", QUICK, "--only", "sim,trian",
                           "--set", f"run.output_dir={json.dumps(str(tmp_path))}"],
                          cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2 and "unknown service 'trian'" in proc.stderr
    assert not any(tmp_path.iterdir())


# --- two hosts on loopback ports ------------------------------------------------------------------------


def host(out_dir, *args: str, name: str, sets=(), joins: helpers.Run | None = None,
         port: int | None = None) -> helpers.Run:
    """One host's `ebrl up` of the quickstart on its own loopback port (``args``: --only, --instance), joining
    the bus of ``joins`` if given."""
    overrides = ['viz.rerun="off"', f"bus.secret_file={json.dumps(str(shared_secret(out_dir.parent)))}", *sets]
    overrides += [f'bus.connect=["{joins.endpoint}"]'] if joins is not None else []
    return helpers.up(out_dir, "configs/quickstart.toml", *overrides, name=name, args=args, port=port)


def summary(out_dir) -> dict:
    (run,) = [p for p in out_dir.iterdir() if p.is_dir()]
    return json.loads((run / "summary.json").read_text())


@pytest.mark.slow
def test_sim_on_another_host_trains_and_the_primary_ends_the_run(tmp_path):
    """`--only`: gen+train as host 0, sim as host 1 joining through host 0's endpoint; a second sim host
    with the same number is refused."""
    with host(tmp_path / "p", "--only", "gen,train", sets=["run.iterations=4"], name="multi") as primary, \
            host(tmp_path / "s", "--only", "sim", "--instance", "1", name="multi", joins=primary) as secondary:
        code = primary.wait(300)
        sim_code = secondary.wait(120)  # it stops once the primary said so
    out, sim_out = primary.output, secondary.output
    assert code == 0, out
    assert sim_code == 0, sim_out
    assert "host 1 joined the run" in out and "the primary host ended the run" in sim_out
    done = summary(tmp_path / "p")
    assert done["iterations"] == 4 and done["env_steps"] > 0 and done["hosts"] == [0, 1]
    assert (tmp_path / "s").glob("*/logs/sim-1.log")


@pytest.mark.slow
def test_the_allocator_on_a_host_without_a_simulator_counts_the_other_hosts(tmp_path):
    """alloc.enabled over two hosts: host 0 (gen, train and the allocator) gives every core to generation and
    training and reads host 1's simulator stats as the rollout capacity it plans with."""
    from ebrl import autotune
    from ebrl.alloc.algorithm import Profiles
    from ebrl.alloc.profile import fingerprint, save
    from ebrl.resources.pool import ResourcePool
    from ebrl.testing import up_sets
    from ebrl.viz import record

    port = helpers.free_port()
    common = ["alloc.enabled=true", "alloc.window=3", "alloc.patience=2"]
    primary_sets = ['viz.rerun="off"', "run.iterations=10", *common]
    cfg = config.load(QUICK, up_sets(tmp_path / "p", port, "multialloc", overrides=primary_sets))  # as the run's
    cfg, _ = autotune.settle(cfg, ("gen", "train", "alloc"), multi=True)  # ... with "auto" decided as there
    pool = ResourcePool(gpu_pool="none")
    n = len(pool.cores)
    profiles = Profiles(sim={(1, e, e): 1000.0 * e for e in range(1, n + 1)},
                        gen={(c, b): 4000.0 * c for c in range(1, n + 1) for b in (4, 8)},
                        train={(c, 1024): 3000.0 * c for c in range(1, n + 1)})
    save(tmp_path / "p" / "profiles" / "multialloc.json", profiles, fingerprint(pool, cfg))
    with host(tmp_path / "p", "--only", "gen,train", sets=primary_sets[1:], name="multialloc", port=port) as primary, \
            host(tmp_path / "s", "--only", "sim", "--instance", "1", sets=common, name="multialloc",
                 joins=primary) as secondary:
        code = primary.wait(300)
        sim_code = secondary.wait(120)
    out, sim_out = primary.output, secondary.output
    assert code == 0, out
    assert sim_code == 0, sim_out
    assert "allocator: reused profile" in out and "sim cores []" in out, out  # no simulator here
    assert "allocator:" not in sim_out  # host 1 runs no allocator
    run = primary.run_dir
    assert "(no simulator on this host)" in (run / "logs" / "alloc-0.log").read_text()
    allocs = [r.metrics for r in record.read(run).stats if r.service == "alloc"]
    assert max(m.get("alloc/sim_hosts", 0) for m in allocs) == 1  # host 1's simulator, seen through the bus
    remote = [m["alloc/remote_sim_capacity"] for m in allocs if "alloc/remote_sim_capacity" in m]
    assert remote and max(remote) > 0, allocs[-1]  # ... and its capacity is what rollout is planned with
    assert all(m["alloc/sim_capacity"] == m["alloc/remote_sim_capacity"] for m in allocs
               if "alloc/remote_sim_capacity" in m)


def test_a_host_number_already_on_the_bus_is_refused(tmp_path):
    with host(tmp_path / "a", "--only", "sim", "--instance", "1", sets=["run.iterations=0"], name="dup") as first:
        first.wait_for_line("all services live", 300)
        with host(tmp_path / "b", "--only", "sim", "--instance", "1", name="dup", joins=first) as second:
            code = second.wait(120)
    assert code == 2 and "host 1 of run dup is already up" in second.output


# --- data-parallel training -----------------------------------------------------------------------------


@pytest.mark.slow  # two real runs of two ranks (the fast suite has DDP's weights after every update, below)
@pytest.mark.parametrize("parallel", ["ddp", "fsdp"])
def test_two_training_ranks_train_and_stop_cleanly(tmp_path, parallel):
    code, out, seen = helpers.run_collecting_stats(tmp_path / "runs", "configs/quickstart.toml", "run.iterations=4",
                                                   "train.world_size=2", f'train.parallel="{parallel}"',
                                                   "train.checkpoint_every=2", 'viz.rerun="off"',
                                                   "policy.normalize_obs=true", run=parallel)
    assert code == 0, out
    assert seen["train/0"][-1]["train/policy_version"] == 4
    assert seen["train/1"][-1]["train/policy_version"] == 4  # every rank took every update
    assert seen["train/1"][-1]["train/batch_size"] > 0  # ... with its own shard
    assert "train/pending_steps" not in seen["train/1"][-1]  # only rank 0 receives trajectories
    (run,) = [p for p in (tmp_path / "runs").iterdir()]
    # rank 1 followed rank 0 to its stop: in its run loop, or, when the launcher's stop came first, while stopping
    assert "rank 0 said stop" in (run / "logs" / "train-1.log").read_text()
    assert (run / "checkpoints" / "v00000004").is_dir() and (run / "policy.safetensors").is_file()
    import numpy as np
    from safetensors.numpy import load_file

    final = load_file(run / "policy.safetensors")
    assert final["obs_norm.count"] > 0 and np.abs(final["obs_norm.mean"]).sum() > 0  # training kept statistics


@pytest.mark.slow
def test_killing_one_rank_restarts_the_training_group(tmp_path):
    import psutil

    with helpers.up(tmp_path / "runs", "configs/quickstart.toml", "run.iterations=40", "train.world_size=2",
                    'viz.rerun="off"', "train.checkpoint_every=2", name="ddpkill") as run:
        deadline = time.monotonic() + 300
        while not (run.run_dir / "checkpoints" / "latest").exists():  # a few updates done
            run.check_running("a checkpoint")
            assert time.monotonic() < deadline, "no checkpoint after 300 s"
            time.sleep(0.2)
        rank1 = [p for p in psutil.Process(run.proc.pid).children()
                 if p.cmdline()[2:3] == ["ebrl.services.train"] and "--instance" in p.cmdline()
                 and p.cmdline()[p.cmdline().index("--instance") + 1] == "1"]
        assert len(rank1) == 1
        rank1[0].kill()
        code = run.wait(600)
    assert code == 0, run.output
    done = json.loads(next((tmp_path / "runs").glob("*/summary.json")).read_text())
    assert done["iterations"] == 40
    assert set(done["restarts"]) == {"train/0", "train/1"}  # the whole group started again


def _ddp_rank(rank: int, world: int, addr: str, out: str, kind: str, shard: bool = False) -> None:
    import torch

    from ebrl.algos.parallel import DataParallel
    from ebrl.algos.ppo import PPO, Batch
    from ebrl.envs.obs import ObsLayout
    from ebrl.policies import make_policy

    torch.manual_seed(rank)  # different initial weights: DDP must start every rank from rank 0's
    policy = make_policy(config.PolicySection(kind=kind, chunk=2, hidden=[16], embed_dim=8, denoise_steps=2,
                                              normalize_obs=True), ObsLayout.vector(3), 2)
    algo = config.AlgoSection(epochs=2, minibatches=3, decoupled=True)
    ppo = PPO(policy, algo, 1e-2, seed=rank)
    before = [p.detach().clone() for p in policy.parameters()]
    dp = DataParallel(policy, ppo.optimizer, rank, world, addr, shard=shard)
    ppo.net, ppo.optimizer = dp.net, dp.optimizer
    g = torch.Generator().manual_seed(100 + rank)  # each rank its own data (and its own size)
    n = 20 + 7 * rank
    batch = Batch(obs=torch.randn(n, 3, generator=g), actions=torch.randn(n, 2, 2, generator=g),
                  latents=torch.randn(n, *policy.latent_shape, generator=g), logprobs=torch.randn(n, generator=g) - 2,
                  advantages=torch.randn(n, generator=g), returns=torch.randn(n, generator=g),
                  values=torch.zeros(n), versions=torch.zeros(n, dtype=torch.long).numpy())
    for _ in range(2):
        # as the train service does: observation statistics from every rank's shard (rank 2 has none) ...
        policy.obs_norm.merge(dp.all_sum(policy.obs_norm.sums(batch.obs[:0] if rank == 2 else batch.obs)))
        ppo.update(batch, scale=0.0 if rank == 2 else 1.0)  # rank 2 got no data: zero gradients, same steps
    with dp.gathered():  # sharded: the policy's own methods see whole parameters inside
        value = policy.value(batch.obs[:2])
    model_state, optim_state = dp.checkpoint_state()
    torch.save({"before": before, "after": dp.full_arrays(), "value": value, "optim": optim_state},
               f"{out}/rank{rank}.pt")
    dp.close()


@pytest.mark.parametrize("kind", ["mlp", "flow"])
def test_ddp_ranks_hold_the_same_weights_after_every_update(tmp_path, kind):
    import torch
    import torch.multiprocessing as mp

    mp.start_processes(_ddp_rank, args=(3, f"127.0.0.1:{helpers.free_port()}", str(tmp_path), kind), nprocs=3,
                       start_method="spawn")
    ranks = [torch.load(tmp_path / f"rank{r}.pt", weights_only=False) for r in range(3)]
    assert ranks[0]["after"]["obs_norm.count"] == 2 * (20 + 27)  # ... added up over the ranks, the same on each
    for r in (1, 2):
        assert ranks[0]["after"].keys() == ranks[r]["after"].keys()
        for name, a in ranks[0]["after"].items():
            assert (a == ranks[r]["after"][name]).all()
    first = torch.load(tmp_path / "rank0.pt", weights_only=False)["before"]
    assert any(not (torch.from_numpy(a) == b).all() for a, b in zip(ranks[0]["after"].values(), first))


@pytest.mark.slow
def test_fsdp_takes_the_same_steps_as_ddp(tmp_path):
    """Sharded parameters, gradients and Adam state: after the same updates on the same shards, the gathered
    weights, values and optimizer state match DDP's."""
    import numpy as np
    import torch
    import torch.multiprocessing as mp

    for shard in (False, True):
        (tmp_path / str(shard)).mkdir()
        mp.start_processes(_ddp_rank, args=(3, f"127.0.0.1:{helpers.free_port()}", str(tmp_path / str(shard)), "mlp",
                                            shard), nprocs=3, start_method="spawn")
    ddp, fsdp = (torch.load(tmp_path / str(shard) / "rank0.pt", weights_only=False) for shard in (False, True))
    assert ddp["after"].keys() == fsdp["after"].keys()
    for name, a in ddp["after"].items():
        np.testing.assert_allclose(fsdp["after"][name], a, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(fsdp["value"], ddp["value"])
    assert fsdp["optim"]["param_groups"] == ddp["optim"]["param_groups"]
    for index, slots in ddp["optim"]["state"].items():
        for key, value in slots.items():
            torch.testing.assert_close(fsdp["optim"]["state"][index][key], value, rtol=1e-5, atol=1e-6)


def test_shards_split_by_decisions():
    from ebrl.algos.parallel import shards

    assert shards([10, 10, 10, 10], lambda x: x, 2) == [[10, 10], [10, 10]]
    assert shards([30, 5, 5, 5, 5], lambda x: x, 2) == [[30], [5, 5, 5, 5]]
    assert shards([7], lambda x: x, 3) == [[7], [], []]


def test_two_ranks_need_a_batch_that_splits():
    with pytest.raises(config.ConfigError, match="train.world_size = 4"):
        load(train={"world_size": 4, "batch_size": 8}, sim={"groups": 1, "envs_per_group": 2})


# --- the router -----------------------------------------------------------------------------------------


def test_ebrl_router_relays_between_hosts_and_prints_who_joined():
    """Two runs' launchers would meet at a router; here two plain sessions that only know the router."""
    import zenoh

    from ebrl import keys
    from ebrl.testing import Output

    port = helpers.free_port()
    router = subprocess.Popen([sys.executable, "-m", "ebrl.cli", "router", "--listen", f"tcp/127.0.0.1:{port}"],
                              cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    printed = Output(router, "ebrl router")
    try:
        printed.wait_for_line("listening on", 120)

        def session() -> zenoh.Session:
            conf = zenoh.Config()
            conf.insert_json5("mode", '"client"')
            conf.insert_json5("scouting/multicast/enabled", "false")
            conf.insert_json5("connect/endpoints", f'["tcp/127.0.0.1:{port}"]')
            return zenoh.open(conf)

        got = []
        with session() as a, session() as b:
            a.declare_subscriber(keys.obs("r"), lambda s: got.append(s.payload.to_bytes()))
            token = b.liveliness().declare_token(keys.live("r", "sim", 3))
            deadline = time.monotonic() + 60
            while not got and time.monotonic() < deadline:
                b.put(keys.obs("r", 0), b"x")
                time.sleep(0.1)
            printed.wait_for_line("run r: sim/3 joined", 60)
            token.undeclare()
            printed.wait_for_line("run r: sim/3 left", 60)
        assert got
    finally:
        router.terminate()
        router.wait(60)
        printed.join()
    assert router.returncode == 0, printed.text


# --- separate hosts: network namespaces -----------------------------------------------------------------


def skip_without_namespaces() -> None:
    """Skip, saying why (in the output, where CI shows it), where hosts cannot be namespaces here."""
    if why := namespaces_unavailable():
        print(f"SKIP namespace test: {why}")
        pytest.skip(why)


def namespaced_run(tmp_path, sims: int, iterations: int) -> tuple[list[str], dict]:
    """One run over ``sims`` + 1 namespaces over TLS: gen+train in ``learner``, one sim host per namespace."""
    hosts = Namespaces(sims)
    try:
        files = tls_files(tmp_path / "tls", hosts)
        cfg = tls_hosts_config(tmp_path, hosts)
        runs = {"learner": hosts.up("learner", cfg, f"run.iterations={iterations}",
                                    *hosts_sets(tmp_path, "learner", files["learner"]))}
        for i in range(sims):
            runs[f"sim-{i}"] = hosts.up(f"sim-{i}", cfg, *hosts_sets(tmp_path, f"sim-{i}", files["sim"]))
        try:
            for name, run in runs.items():
                run.proc.wait(timeout=240)
                run.join()
        finally:
            for run in runs.values():
                run.proc.kill()
        for name, run in runs.items():
            assert run.proc.returncode == 0, f"{name}:\n{run.text}"
        return [run.text for run in runs.values()], summary(tmp_path / "learner")
    finally:
        hosts.close()


@pytest.mark.slow
def test_sim_and_learner_in_separate_network_namespaces_train(tmp_path):
    skip_without_namespaces()
    (learner, sim), done = namespaced_run(tmp_path, sims=1, iterations=4)
    assert done["iterations"] == 4 and done["env_steps"] > 0 and done["segments"] > 0
    assert "host 1 joined the run" in learner and "the primary host ended the run" in sim


def attempt(hosts: Namespaces, cfg, tmp_path, config_file: str, secret=None) -> tuple[int, str, float, float]:
    """sim-0 tries to join: its exit status, its output, the seconds from its start to its exit, and from its
    launcher's first line (the run's banner; 0 where it stopped before) to its exit."""
    started = time.monotonic()
    run = hosts.up("sim-0", cfg, *hosts_sets(tmp_path, "sim-0", config_file, secret))
    banner = None
    try:
        try:
            run.wait_for_line("run netns: ", 120)
            banner = time.monotonic()
        except RuntimeError:  # it stopped before its launcher started
            pass
        run.proc.wait(timeout=120)
    finally:
        run.proc.kill()
    ended = time.monotonic()
    run.join()
    return run.proc.returncode, run.text, ended - started, ended - (banner or ended)


@pytest.mark.slow
def test_three_hosts_over_tls_refuse_what_cannot_join_and_survive_a_kill_and_an_outage(tmp_path):
    """Hosts in network namespaces (192.0.2.0/24), TLS between them. Before the run moves: a sim host with the
    certificate of another CA, with no CA, with another run's secret and with no secret file each stops with
    exit 2 and the cause within 15 s, and the learner says it refused one; then two sim hosts run, one is
    killed (kill -9 of its launcher) and started again, the other loses its link for 20 s, and the run ends
    for every host with exit 0."""
    import signal

    skip_without_namespaces()
    hosts = Namespaces(2)
    try:
        files = tls_files(tmp_path / "tls", hosts)
        cfg = tls_hosts_config(tmp_path, hosts)
        learner = hosts.up("learner", cfg, "run.iterations=40", "train.checkpoint_every=0",
                           *hosts_sets(tmp_path, "learner", files["learner"]))
        try:
            learner.wait_for_line("all services live", 300)
            from ebrl.bus import auth

            other = auth.create(tmp_path / "other.secret")
            cases = [(files["wrong"], None, "its certificate does not verify against the CA in root_ca_certificate",
                      "refused at the TLS handshake"),
                     (files["none"], None, "the system's CAs (bus.config_file names no root_ca_certificate)", None),
                     (files["sim"], other, f"refused this host's sign-in: bus.secret_file = {str(other)!r}",
                      "was refused at sign-in"),
                     (files["sim"], tmp_path / "missing.secret", "no such file; a host that joins a run signs in "
                      "with the primary host's secret", None)]
            for config_file, secret, cause, refused in cases:
                code, out, total_s, launcher_s = attempt(hosts, cfg, tmp_path, config_file, secret)
                assert code == 2 and cause in out, out
                print(f"exit 2 after {total_s:.1f} s ({launcher_s:.1f} s of it the launcher's): {cause}")
                assert launcher_s <= 15.0, out  # the launcher's part: `ebrl up`'s imports come before it
                if refused:
                    learner.wait_for_line(refused, 30)
            sims = {name: hosts.up(name, cfg, *hosts_sets(tmp_path, name, files["sim"])) for name in ("sim-0", "sim-1")}
            learner.wait_for_line(lambda line: "iter " in line and int(line.split("iter ")[1].split("/")[0]) >= 3,
                                  300, "iteration 3")
            os.kill(sims["sim-0"].proc.pid, signal.SIGKILL)  # `ip netns exec` became the launcher
            learner.wait_for_line("host 1 left the run", 60)
            sims["sim-0"] = hosts.up("sim-0", cfg, *hosts_sets(tmp_path, "sim-0", files["sim"]))
            sims["sim-0"].wait_for_line("all services live", 300)
            hosts.link("sim-1", up=False)
            time.sleep(20)
            hosts.link("sim-1", up=True)
            assert learner.proc.wait(timeout=600) == 0, learner.text
            for name, run in sims.items():
                assert run.proc.wait(timeout=120) == 0, f"{name}:\n{run.text}"
                assert "the primary host ended the run" in run.text
        finally:
            for run in [learner, *locals().get("sims", {}).values()]:
                run.proc.kill()
        assert learner.text.count("host 1 joined the run") == 2, learner.text
        assert summary(tmp_path / "learner")["iterations"] == 40
    finally:
        hosts.close()


@pytest.mark.slow
def test_two_training_ranks_on_two_hosts_hold_the_same_weights_and_a_lost_rank_stops_the_run(tmp_path):
    """Training rank 0 on the learner, rank 1 on the simulation host (namespaces, TLS for the bus, gloo over the
    trusted link): the run finishes on both hosts, every update checked on the ranks themselves to leave them
    with the same weights (train/ranks_checked, none in train/ranks_diverged). A rendezvous outside the trusted
    networks is refused before anything starts. Then the second host is killed mid-run: the learner says which
    rank left and stops (exit 1), as docs/scaling-out.md says."""
    import signal

    from ebrl.viz import record

    skip_without_namespaces()
    hosts = Namespaces(1)
    try:
        files = tls_files(tmp_path / "tls", hosts)
        cfg = ranks_across_hosts_config(tmp_path, hosts)
        (tmp_path / "u").mkdir()
        untrusted = ranks_across_hosts_config(tmp_path / "u", hosts, trusted="10.0.0.0/8")
        refused = hosts.up("learner", untrusted, *hosts_sets(tmp_path / "u", "learner", files["learner"]))
        assert refused.proc.wait(timeout=120) == 2
        refused.join()
        assert "is outside train.trusted_networks (10.0.0.0/8)" in refused.text, refused.text

        runs = {"learner": hosts.up("learner", cfg, "run.iterations=6", *hosts_sets(tmp_path, "learner",
                                                                                      files["learner"])),
                "sim-0": hosts.up("sim-0", cfg, "run.iterations=6", *hosts_sets(tmp_path, "sim-0", files["sim"]))}
        try:
            for name, run in runs.items():
                assert run.proc.wait(timeout=600) == 0, f"{name}:\n{run.text}"
        finally:
            for run in runs.values():
                run.proc.kill()
        (learner_dir,) = [p for p in (tmp_path / "learner").iterdir() if p.is_dir()]
        reports = [r.metrics for r in record.read(learner_dir).stats if r.service == "train" and r.instance == 0]
        last = reports[-1]
        assert last["train/updates"] >= 6 and last["train/ranks_checked"] == last["train/updates"], last
        assert "train/ranks_diverged" not in last
        assert any(r.service == "train" and r.instance == 1 for r in record.read(learner_dir).stats)  # rank 1 seen
        print(f"two hosts, two ranks: {last['train/updates']:.0f} updates, each checked ({runs['learner'].text.strip().splitlines()[-2]})")

        runs = {"learner": hosts.up("learner", cfg, "run.iterations=0", *hosts_sets(tmp_path / "k", "learner",
                                                                                      files["learner"])),
                "sim-0": hosts.up("sim-0", cfg, "run.iterations=0", *hosts_sets(tmp_path / "k", "sim-0", files["sim"]))}
        try:
            runs["learner"].wait_for_line(lambda line: "iter " in line and int(line.split("iter ")[1].split()[0]) >= 2,
                                          300, "iteration 2")
            os.kill(runs["sim-0"].proc.pid, signal.SIGKILL)
            assert runs["learner"].proc.wait(timeout=120) == 1
            runs["learner"].join()
            assert "training rank train/1 of another host left the run" in runs["learner"].text, runs["learner"].text
            print([line for line in runs["learner"].text.splitlines() if "train/1" in line][:2])
        finally:
            for run in runs.values():
                run.proc.kill()
    finally:
        hosts.close()


@pytest.mark.slow
def test_two_training_ranks_learn_the_quickstart_like_one(tmp_path):
    """The quickstart's stated threshold (mean return 900) with train.world_size = 2, as one rank reaches it
    (tests/test_up.py::test_quickstart_learns_to_the_stated_return); curves side by side:
    benchmarks/data_parallel.py."""
    with helpers.up(tmp_path / "runs", "configs/quickstart.toml", "train.world_size=2", 'viz.rerun="off"',
                    name="learn2") as run:
        assert run.wait(900) == 0, run.output
    done = json.loads((run.run_dir / "summary.json").read_text())
    assert done["target_reached"] is not None, run.output
    assert done["target_reached"]["return"] >= 900


@pytest.mark.slow
def test_a_late_host_is_admitted_and_a_host_that_leaves_is_not_waited_for(tmp_path):
    """Host 1 simulates from the start; host 2 joins mid-run; host 1 is killed (its launcher SIGKILLed, its
    services follow it); the run finishes on host 2."""
    import signal

    primary = host(tmp_path / "p", "--only", "gen,train", sets=["run.iterations=30", "train.checkpoint_every=0"],
                   name="churn")

    def sim_host(n: int) -> helpers.Run:
        return host(tmp_path / f"h{n}", "--only", "sim", "--instance", str(n), name="churn", joins=primary)

    def at_iteration(n: int):
        return lambda line: "iter " in line and int(line.split("iter ")[1].split("/")[0]) >= n

    with primary, sim_host(1) as first:
        primary.wait_for_line(at_iteration(3), 600, "iteration 3")
        with sim_host(2) as second:
            primary.wait_for_line("host 2 joined the run", 300)
            second.wait_for_line("all services live", 300)
            time.sleep(5)  # let host 2 simulate a while
            os.kill(first.proc.pid, signal.SIGKILL)
            code = primary.wait(900)
            second_code = second.wait(120)
    out = primary.output
    assert code == 0, out
    assert "host 1 joined the run" in out and "host 2 joined the run" in out and "host 1 left the run" in out
    assert summary(tmp_path / "p")["iterations"] == 30
    assert "the primary host ended the run" in second.output and second_code == 0, second.output
