"""Hosts as Linux network namespaces joined by their own veth links (addresses from 192.0.2.0/24), TLS between
them with certificates made by openssl: what tests/test_hosts.py and benchmarks/hosts_netns.py run a run over
several hosts on. Needs root and iproute2 (``namespaces_unavailable`` says why not)."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import uuid
from pathlib import Path

import tlscerts
from ebrl.testing import Output

ROOT = Path(__file__).resolve().parent.parent


def shared_secret(where):
    """The one secret file the hosts of a test's run share (bus.secret_file), created on first use."""
    from ebrl.bus import auth

    where.mkdir(parents=True, exist_ok=True)
    return auth.ensure(where / "shared.secret")



def _netns_unavailable() -> str | None:
    if sys.platform != "linux":
        return "network namespaces are Linux only"
    if shutil.which("ip") is None:
        return "the `ip` command (iproute2) is not installed"
    if os.geteuid() != 0:
        return "creating network namespaces needs root"
    name = f"ebrl-probe-{os.getpid()}"
    made = subprocess.run(["ip", "netns", "add", name], capture_output=True, text=True)
    if made.returncode != 0:
        return f"cannot create a network namespace here: {made.stderr.strip()}"
    subprocess.run(["ip", "netns", "del", name], capture_output=True)
    return None


class Namespaces:
    """Hosts as network namespaces: a ``learner`` joined to each sim host by its own veth link, addresses from
    192.0.2.0/24 (TEST-NET-1: a /30 per link), nothing else reachable."""

    def __init__(self, sims: int):
        tag = uuid.uuid4().hex[:6]
        self.names = {"learner": f"ebrl-{tag}-l", **{f"sim-{i}": f"ebrl-{tag}-s{i}" for i in range(sims)}}
        self.addresses: dict[str, str] = {}  # sim host -> the learner's address on its link
        self.links: dict[str, str] = {}  # sim host -> the learner's end of its link
        for ns in self.names.values():
            self.ip("netns", "add", ns)
            self.ip("-n", ns, "link", "set", "lo", "up")
        learner = self.names["learner"]
        for i in range(sims):
            sim, a, b = self.names[f"sim-{i}"], f"vl{tag}{i}", f"vs{tag}{i}"
            self.ip("link", "add", a, "type", "veth", "peer", "name", b)
            self.ip("link", "set", a, "netns", learner)
            self.ip("link", "set", b, "netns", sim)
            self.ip("-n", learner, "addr", "add", f"192.0.2.{4 * i + 1}/30", "dev", a)
            self.ip("-n", sim, "addr", "add", f"192.0.2.{4 * i + 2}/30", "dev", b)
            for ns, dev in ((learner, a), (sim, b)):
                self.ip("-n", ns, "link", "set", dev, "up")
            self.addresses[f"sim-{i}"] = f"192.0.2.{4 * i + 1}"
            self.links[f"sim-{i}"] = a

    @staticmethod
    def ip(*args: str) -> None:
        subprocess.run(["ip", *args], check=True, capture_output=True)

    def link(self, host: str, up: bool) -> None:
        """Take ``host``'s link to the learner down or up again."""
        self.ip("-n", self.names["learner"], "link", "set", self.links[host], "up" if up else "down")

    def popen(self, host: str, cmd: list[str]) -> subprocess.Popen:
        env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))}
        return subprocess.Popen(["ip", "netns", "exec", self.names[host], *cmd], cwd=ROOT, stdout=subprocess.PIPE,
                                stderr=subprocess.STDOUT, text=True, env=env)

    def up(self, host: str, cfg, *sets: str) -> Output:
        """``ebrl up CFG --host HOST`` in ``host``'s namespace, its output read as it comes."""
        proc = self.popen(host, [sys.executable, "-m", "ebrl.cli", "up", str(cfg), "--host", host,
                                 *[arg for value in sets for arg in ("--set", value)]])
        return Output(proc, f"host {host}")

    def close(self) -> None:
        for ns in self.names.values():  # deleting a namespace deletes its veth ends
            subprocess.run(["ip", "netns", "del", ns], capture_output=True)


def tls_files(where, hosts: Namespaces) -> dict[str, str]:
    """The run's CA and the learner's certificate (for each of its addresses), another CA, and a Zenoh config
    file per case: the learner's, a sim host's, one naming the other CA, one naming none."""
    right, wrong = tlscerts.make_ca(where, "run-ca"), tlscerts.make_ca(where, "other-ca")
    cert = tlscerts.make_cert(where, right, "learner", list(hosts.addresses.values()))
    return {"learner": str(tlscerts.zenoh_tls(where / "learner.json5", right, cert)),
            "sim": str(tlscerts.zenoh_tls(where / "sim.json5", right)),
            "wrong": str(tlscerts.zenoh_tls(where / "wrong.json5", wrong)),
            "none": str(tlscerts.zenoh_tls(where / "none.json5", None))}


def tls_hosts_config(tmp_path, hosts: Namespaces) -> Path:
    """The quickstart over the namespaces: gen and train on the learner, which listens on TLS on each link's
    address; a sim host per link, connecting there, its own services on its loopback."""
    listen = [f"tls/{address}:7447" for address in hosts.addresses.values()]
    table = [f'[hosts.learner]\nservices = ["gen", "train"]\nlisten = {json.dumps(listen)}\n']
    for sim, address in hosts.addresses.items():
        table.append(f'[hosts.{sim}]\nservices = ["sim"]\nconnect = ["tls/{address}:7447"]\n'
                     'listen = ["tcp/127.0.0.1:7447"]\n')
    cfg = tmp_path / "hosts.toml"
    cfg.write_text((ROOT / "configs" / "quickstart.toml").read_text() + "\n" + "\n".join(table))
    return cfg


def hosts_sets(tmp_path, host: str, config_file: str, secret=None) -> list[str]:
    """The --set values of one host: its own output directory, config file and the run's shared secret."""
    secret = secret or shared_secret(tmp_path)
    return ['viz.rerun="off"', "run.stats_interval=0.5", "run.name=netns", f"bus.secret_file={json.dumps(str(secret))}",
            f"bus.config_file={json.dumps(config_file)}", f"run.output_dir={json.dumps(str(tmp_path / host))}"]


def namespaces_unavailable() -> str | None:
    return _netns_unavailable() or tlscerts.unavailable()


def ranks_across_hosts_config(tmp_path, hosts: Namespaces, trusted: str = "192.0.2.0/24") -> Path:
    """The quickstart with two training ranks: rank 0 with generation on the learner, rank 1 with the
    simulator on sim-0; they meet at the learner's address on the link, a network declared trusted."""
    address = hosts.addresses["sim-0"]
    cfg = tmp_path / "ranks.toml"
    cfg.write_text((ROOT / "configs" / "quickstart.toml").read_text().replace("[train]\n", f"""[train]
world_size = 2
rendezvous = "{address}:29511"
trusted_networks = ["{trusted}"]
""") + f"""
[hosts.learner]
services = ["gen", "train"]
listen = ["tls/{address}:7447"]

[hosts.sim-0]
services = ["train", "sim"]
connect = ["tls/{address}:7447"]
listen = ["tcp/127.0.0.1:7447"]
""")
    return cfg
