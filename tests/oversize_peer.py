"""Oversized messages against a receiver's bounds (issue 52, ebrl/sizes.py).

    python tests/oversize_peer.py probe CONFIG ENDPOINT LIMIT

A subscriber of a run's observations as generation is one: a service whose bounds come from CONFIG's shapes
(LIMIT ``run``: ``ebrl.sizes``, as gen's; ``bus``: none, only bus.max_message_bytes, as before) joins the bus at
ENDPOINT and decodes what arrives on ``ebrl/data/<run>/obs/*`` like gen. Once it received an observation of seq
0 it prints its peak memory (``ready`` and VmHWM in kB); once one of seq 2, a JSON line of its peak memory, the seqs
it received and its bus's counts (malformed, oversized), and exits.

    python tests/oversize_peer.py send WHO ENDPOINT RUN_DIR KEY BYTES [BYTES ...]

Signed in as WHO (``ROLE/N``: that instance's own line, as its launcher hands it; ``ROLE``: the role's line of
the run's secret) at ENDPOINT, it publishes on KEY one observation of about each BYTES (env ids and 4 floats per
env; ``junk``: 64 bytes that decode as nothing, which a receiver counts as malformed once it has everything sent
before), with blocking congestion control (as an attacker would: a dropping put loses a large message on the
way), and prints how long each put took.
"""

from __future__ import annotations

import asyncio
import json
import os
import sys
import time

import numpy as np

from ebrl import config as config_mod, obswire, sizes
from ebrl import keys
from ebrl.bus import auth
from ebrl.bus.session import BusOptions
from ebrl.messages import Observation, encode_message
from ebrl.service import Service, env_info


def peak_kb(pid: int | str = "self") -> int:
    """VmHWM of a process: its peak resident memory so far, in kB."""
    with open(f"/proc/{pid}/status") as fh:
        for line in fh:
            if line.startswith("VmHWM:"):
                return int(line.split()[1])
    raise RuntimeError(f"no VmHWM in /proc/{pid}/status")


def observation(nbytes: int, seq: int) -> bytes:
    """An observation of a state policy of 4 floats, of about ``nbytes`` (an env id and 4 floats per env)."""
    envs = max(1, nbytes // 24)
    return encode_message(Observation(group=0, seq=seq, env_ids=np.arange(envs, dtype=np.int64),
                                      obs=np.zeros((envs, 4), np.float32), sent_at=time.time()))


class ObsProbe(Service):
    """Generation's receiving side alone: its bounds, its subscription of observations, its decoder."""

    role = "gen"

    def __init__(self, cfg: config_mod.Config, options: BusOptions, limit: str):
        super().__init__(cfg, 0, options)
        self.limit = limit

    async def message_bounds(self) -> sizes.Bounds | None:
        if self.limit == "bus":
            return None
        return sizes.of_run(self.cfg, await env_info(self), weights=True)

    async def setup(self) -> None:
        info = await env_info(self)
        self.obs = self.bus.subscribe(keys.obs(self.run_name), obswire.decoder(Observation, info.layout,
                                                                               info.obs_shape),
                                      max_bytes=self.bounds.obs if self.bounds else None)

    async def run(self) -> None:
        seqs: list[int] = []
        before = None
        async for _, msg in self.obs:
            seqs.append(msg.seq)
            if msg.seq == 0 and before is None:
                before = peak_kb()
                print("ready", before, flush=True)
            if msg.seq == 2:
                break
        print(json.dumps({"before_kb": before, "after_kb": peak_kb(), "seqs": sorted(set(seqs)),
                          "link_bytes": self.bus.options.max_message_bytes,
                          "oversized": sum(self.bus.oversized.values()),
                          "malformed": sum(self.bus.malformed.values())}), flush=True)


def main_probe(config_path: str, endpoint: str, limit: str) -> int:
    cfg = config_mod.load(config_path, ["bus.auth=false"])
    options = BusOptions(mode="client", connect=[endpoint], listen=[], max_message_bytes=cfg.bus.max_message_bytes)
    return asyncio.run(ObsProbe(cfg, options, limit).main(signals=False))


def main_send(who: str, endpoint: str, run_dir: str, key: str, *sizes_: str) -> int:
    import zenoh

    from ebrl.bus.session import zenoh_config

    role, _, instance = who.partition("/")
    secret = os.path.join(run_dir, auth.FILENAME)
    identity = auth.instance_line(secret, role, int(instance)) if instance else ""  # as its launcher hands it
    session = zenoh.open(zenoh_config(BusOptions(mode="client", connect=[endpoint], listen=[], secret_file=secret,
                                                 role=role, identity=identity)))
    puts = []
    for seq, size in enumerate(sizes_):
        payload = b"\xc1" * 64 if size == "junk" else observation(int(size), 10**6 + seq)
        start = time.monotonic()
        session.put(key, payload, congestion_control=zenoh.CongestionControl.BLOCK)
        puts.append({"bytes": len(payload), "seconds": round(time.monotonic() - start, 3)})
        del payload
    time.sleep(1.0)  # the last fragments leave the socket before the session closes
    print(json.dumps({"puts": puts, "routers": len(list(session.info.routers_zid()))}), flush=True)
    session.close()
    os._exit(0)


def service_pids(run) -> dict[str, int]:
    """The pids of a live run's gen and train processes (children of its launcher)."""
    import psutil

    pids = {}
    for child in psutil.Process(run.proc.pid).children(recursive=True):
        try:
            cmdline = child.cmdline()
        except psutil.NoSuchProcess:
            continue
        for role in ("gen", "train"):
            if f"ebrl.services.{role}" in cmdline:
                pids[role] = child.pid
    return pids


def attack(run, stats, env: dict[str, str]) -> dict:
    """For a test against a live quickstart (``run``, its ``stats`` watcher): once training is under way, sim/0
    sends an observation of 600 kB and junk, then one of 240 MiB and junk; gen's and train's peak memory read
    before the 240 MiB one and once gen counted the junk after it (one key, one publisher: in order). The 600 kB
    one goes first and apart: under gen's receive limit and over its key's bound, Zenoh reassembles it and it is
    dropped before it is copied, about 19 MB of gen's peak once. Returns what was sent and the memory read."""
    import subprocess

    from ebrl import keys

    def send(*sizes_: str) -> dict:
        sender = subprocess.run([sys.executable, __file__, "send", "sim/0", run.endpoint, str(run.run_dir),
                                 keys.obs(run.name, 0), *sizes_], capture_output=True, text=True, env=env, timeout=300)
        assert sender.returncode == 0, sender.stderr[-3000:]
        return json.loads(sender.stdout)

    stats.wait_for(lambda: (stats.latest("train/0", "train/policy_version") or 0) >= 5, 300, "policy v5")
    pids = service_pids(run)
    first = send("600000", "junk")
    stats.wait_for(lambda: (stats.latest("gen/0", "bus/malformed") or 0) >= 2, 120, "gen counting the junk")
    before = {role: peak_kb(pid) for role, pid in pids.items()}
    big = send(str(240 << 20), "junk")
    stats.wait_for(lambda: (stats.latest("gen/0", "bus/malformed") or 0) >= 3, 120, "gen counting the junk")
    return {"first": first, "big": big, "pids": pids, "before": before,
            "after": {role: peak_kb(pid) for role, pid in pids.items()}}


if __name__ == "__main__":
    mode, args = sys.argv[1], sys.argv[2:]
    sys.exit(main_probe(*args) if mode == "probe" else main_send(*args))
