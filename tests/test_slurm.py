"""Runs on a cluster (ebrl.slurm): Slurm's host lists and task layout, the placeholders of a [hosts] table, the
batch script against the one docs/scaling-out.md shows, a Kubernetes Indexed Job's index; and, slow, a real
single-node Slurm (tests/slurm_cluster.py): the script of a short quickstart to its end, and `srun` starting
two hosts of a [hosts] run over TLS directly."""

from __future__ import annotations

import json
import re
import socket
import sys
import time
import tomllib

import pytest

import helpers
import slurm_cluster
import tlscerts
from ebrl import config, slurm
from ebrl.config import ConfigError

ROOT = helpers.ROOT
DOCS = ROOT / "docs" / "scaling-out.md"


def test_host_lists_and_tasks_per_node_expand_as_slurm_writes_them():
    assert slurm.expand_nodelist("node[01-03,07],gpu5") == ["node01", "node02", "node03", "node07", "gpu5"]
    assert slurm.expand_nodelist("vm") == ["vm"]
    assert slurm.expand_nodelist("a[8-10]-ib") == ["a8-ib", "a9-ib", "a10-ib"]
    assert slurm.tasks_per_node("2(x3),1") == [2, 2, 2, 1]
    env = {"SLURM_JOB_NODELIST": "n[1-3]", "SLURM_TASKS_PER_NODE": "2,1(x2)"}
    assert [slurm.node_of_task(t, env) for t in range(4)] == ["n1", "n1", "n2", "n3"]
    with pytest.raises(ValueError):
        slurm.node_of_task(4, env)
    with pytest.raises(ValueError, match="not a Slurm host list"):
        slurm.expand_nodelist("n[3-1]")


def hosts_config(**extra) -> config.Config:
    return config.from_dict({"viz": {"rerun": "off"}, "hosts": {
        "learner": {"services": ["gen", "train"], "listen": ["tls/{primary}:7447"]},
        "sim-a": {"services": ["sim"], "connect": ["tls/{primary}:7447"], "listen": ["tcp/127.0.0.1:{node}"]},
        "sim-b": {"services": ["sim"], "connect": ["tls/{primary}:7447"]}}, **extra})


def srun_env(rank: int, tasks: int = 3, nodes: str = "c[07-09]", per_node: str = "1(x3)") -> dict[str, str]:
    return {"SLURM_PROCID": str(rank), "SLURM_STEP_ID": "0", "SLURM_NTASKS": str(tasks), "SLURM_JOB_NODELIST": nodes,
            "SLURM_TASKS_PER_NODE": per_node}


def test_under_srun_task_i_runs_entry_i_with_the_primary_s_node_filled_in():
    cfg = hosts_config()
    for rank, name in enumerate(["learner", "sim-a", "sim-b"]):
        filled, host = slurm.placement(cfg, None, None, None, srun_env(rank))
        assert host == name
        assert filled.hosts["learner"].listen == ["tls/c07:7447"] and filled.hosts["sim-b"].connect == ["tls/c07:7447"]
        assert filled.hosts["sim-a"].listen == [f"tcp/127.0.0.1:c0{7 + rank}"]  # {node}: this task's own
    # the command line's part wins; one task is a one-host run
    assert slurm.placement(cfg, "sim-b", None, None, srun_env(0))[1] == "sim-b"
    single = config.from_dict({"bus": {"listen": ["tls/{node}:7447"]}})
    filled, host = slurm.placement(single, None, None, None, srun_env(0, tasks=1, nodes="gpu3", per_node="1"))
    assert host is None and filled.bus.listen == ["tls/gpu3:7447"]


def test_what_does_not_fit_slurm_is_a_config_error_naming_it():
    with pytest.raises(ConfigError, match=r"under srun with 2 tasks, task i runs the i-th entry of \[hosts\]: the "
                                          r"config has 3 \(learner, sim-a, sim-b\)"):
        slurm.placement(hosts_config(), None, None, None, srun_env(0, tasks=2))
    with pytest.raises(ConfigError, match=r"hosts.learner.listen: \{primary\} and \{node\} are filled in only in a "
                                          r"task that srun started"):
        slurm.placement(hosts_config(), "learner", None, None, {})
    with pytest.raises(ConfigError, match=r"--nodes 2: node i runs the i-th entry of \[hosts\], and the config has 3"):
        slurm.batch_script("c.toml", hosts_config(), [], 2)


def test_a_kubernetes_indexed_job_s_pod_runs_the_entry_of_its_index():
    cfg = config.from_dict({"hosts": {"learner": {"services": ["gen", "train"]}, "sim": {"services": ["sim"]}}})
    assert slurm.placement(cfg, None, None, None, {"JOB_COMPLETION_INDEX": "1"})[1] == "sim"
    assert slurm.placement(cfg, "learner", None, None, {"JOB_COMPLETION_INDEX": "1"})[1] == "learner"
    with pytest.raises(ConfigError, match="JOB_COMPLETION_INDEX = 2: the config's \\[hosts\\] has 2 entries"):
        slurm.placement(cfg, None, None, None, {"JOB_COMPLETION_INDEX": "2"})


def _block(marker: str) -> str:
    text = DOCS.read_text()
    return re.search(rf"<!-- {marker} -->\n```\w+\n(.*?)```", text, re.S)[1]


def test_the_batch_script_is_the_one_the_docs_show_for_their_config():
    """docs/scaling-out.md's three-node example: its config (over the quickstart) gives its script exactly."""
    raw = tomllib.loads((ROOT / "configs" / "quickstart.toml").read_text())
    for section, values in tomllib.loads(_block("slurm-config")).items():
        raw.setdefault(section, {}).update(values)
    script = slurm.batch_script("configs/my_run.toml", config.from_dict(raw), [], 3, "cpu", "2:00:00",
                                python="python", cwd="/home/me/ebrl")
    assert script == _block("slurm-script")
    assert "#SBATCH --nodes=3\n#SBATCH --ntasks-per-node=1\n" in script
    assert script.rstrip().splitlines()[-1].startswith("srun --kill-on-bad-exit=1 ")


# --- a real Slurm ----------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    if why := slurm_cluster.unavailable():
        print(f"SKIP Slurm tests: {why}")
        pytest.skip(why)
    running = slurm_cluster.Cluster(tmp_path_factory.mktemp("slurm"))
    yield running
    running.close()


@pytest.mark.slow
def test_ebrl_slurm_submits_a_job_that_runs_the_quickstart_to_its_end(cluster, tmp_path):
    done = cluster.run(sys.executable, "-m", "ebrl.cli", "slurm", str(ROOT / "configs" / "quickstart.toml"), "--set", "run.iterations=3",
                       "--set", 'viz.rerun="off"', "--submit", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    job = done.stdout.split("submitted: job ")[1].split()[0]
    state = cluster.wait_job(job, 600)
    assert state == "COMPLETED", [p.read_text() for p in (tmp_path / "runs").glob("slurm-*.out")]
    (out,) = (tmp_path / "runs").glob(f"slurm-{job}.out")
    (run_dir,) = [p for p in (tmp_path / "runs").iterdir() if p.is_dir()]
    assert json.loads((run_dir / "summary.json").read_text())["iterations"] == 3, out.read_text()


@pytest.mark.slow
def test_srun_starts_two_hosts_of_a_hosts_run_over_tls_on_the_primary_s_node(cluster, tmp_path):
    """Two tasks on the one node this cluster has: the learner listens on TLS at {primary} (the node's name,
    which its certificate carries), the simulation host connects there, and takes a free port for its own
    services (the learner's launcher shares the machine)."""
    if why := tlscerts.unavailable():
        pytest.skip(why)
    node = socket.gethostname()
    try:
        socket.gethostbyname(node)
    except OSError:
        pytest.skip(f"this machine's name {node!r} does not resolve: {{primary}} would name no address")
    ca = tlscerts.make_ca(tmp_path / "tls", "ca")
    cert, key = tlscerts.make_cert(tmp_path / "tls", ca, "learner", [], dns=[node])
    zfile = tlscerts.zenoh_tls(tmp_path / "z.json5", ca, (cert, key))
    port = helpers.free_port()
    cfg = tmp_path / "hosts.toml"
    cfg.write_text((ROOT / "configs" / "quickstart.toml").read_text() + f"""
[hosts.learner]
services = ["gen", "train"]
listen = ["tls/{{primary}}:{port}"]

[hosts.sim-0]
services = ["sim"]
connect = ["tls/{{primary}}:{port}"]
""")
    from ebrl.bus import auth

    secret = auth.create(tmp_path / "run.secret")
    started = time.monotonic()
    done = cluster.run("srun", "--ntasks=2", "--overcommit", "--kill-on-bad-exit=1", "--time=10",
                       sys.executable, "-m", "ebrl.cli", "up", str(cfg), "--set", "run.iterations=3", "--set", 'viz.rerun="off"',
                       "--set", f"bus.config_file={json.dumps(str(zfile))}",
                       "--set", f"bus.secret_file={json.dumps(str(secret))}",
                       "--set", f"run.output_dir={json.dumps(str(tmp_path / 'runs'))}", cwd=tmp_path)
    out = done.stdout + done.stderr
    assert done.returncode == 0, out
    print(f"srun: two hosts, 3 iterations in {time.monotonic() - started:.0f} s")
    assert f"(host learner: log, train, gen; bus tls/{node}:{port})" in out
    assert "host 1 joined the run" in out and "the primary host ended the run" in out
    dirs = sorted(p.name for p in (tmp_path / "runs").iterdir())
    assert len(dirs) == 2 and dirs[1] == dirs[0] + "-sim-0"  # side by side, the joining host's named after it
