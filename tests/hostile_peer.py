"""A hostile process on the same machine as a run: joins the run's bus at its endpoint and, until the run's
launcher is gone, tries to read its data and to stop, poison and end it. Prints one JSON line of what it got.

    python tests/hostile_peer.py ENDPOINT RUN RUN_DIR

It has no credentials: it tries to read RUN_DIR/bus.secret, as an outsider would, and joins without. It stops
when its standard input closes.

    python tests/hostile_peer.py --insider ROLE[/N] ENDPOINT RUN RUN_DIR

An insider: signed in with ROLE/N's own line, as the run's launcher hands it to that process (a line that
leaked, or a user's env code in that process), or with ROLE's line of the run's secret (what a service of a
mesh signs in with), it sends until its standard input closes what another role owns, each message
well formed and plausible, so that only the bus's access rules can stop it: the policy's own tensors zeroed at
plausible versions (weights), training's and the simulators' reports of a return no run reaches, quotas,
affinities and GPU shares at version 2**53, a GPU share naming CUDA_INJECTION64_PATH, stops for every service,
a second trainer's liveliness token; and as 63 more instances of its own role (``OTHERS``, the run has one):
their liveliness tokens (63 simulator hosts would stall generation's schedule) and their stats reports. Each
forged message is marked (:func:`mark`, ``MARK_TIME``, ``MARK_REASON``) so the test can tell it apart. What ROLE
owns itself (sim's reports, for a sim insider) passes the rules: the run must not believe it.

    python tests/hostile_peer.py --claims ROLE[/N] ENDPOINT RUN RUN_DIR

The same insider making only the claims to be 63 more instances of its role (their tokens and reports).

    python tests/hostile_peer.py --crafted ENDPOINT RUN SECONDS

On a run whose bus is open (bus.auth = false), what validation alone must stop: for SECONDS, messages made
from the run's own traffic with poisoned meaning (NaN rewards and weights, far-future versions, ragged
fields, forged reports), payloads crafted against the decoder, and 8 MB of garbage.
"""

from __future__ import annotations

import json
import os
import sys
import threading
import time

import zenoh

from ebrl import keys
from ebrl.bus import auth
from ebrl.bus.session import BusOptions, zenoh_config
from ebrl.messages import StatsReport, Stop, Weights, encode_message


def attacks(run: str) -> list[tuple[str, bytes]]:
    """What it publishes, each a well-formed message: if one arrived, the run would show it."""
    now = time.time()
    out = [(keys.ctl(run, role, 0, "stop"), encode_message(Stop(reason="hostile stop")))
           for role in ("train", "gen", "sim", "launcher")]
    out.append((keys.ctl(run, "launcher", "all", "stop"), encode_message(Stop(reason="hostile stop"))))
    # a weights version far ahead: generation would ignore every real update after it
    out.append((keys.weights(run), encode_message(Weights(version=10**9, params={}, created_at=now))))
    # a made-up training report of a late version: the launcher would end the run as finished
    out.append((keys.stats(run, "train", 9), encode_message(StatsReport(
        run=run, service="train", instance=9, time=now, seq=0,
        metrics={"train/policy_version": 10.0**6, "train/iteration": 10.0**6}))))
    out.append((keys.traj(run, 0), os.urandom(64)))
    return out


def crafted(run: str, seen: dict[str, bytes]) -> list[tuple[str, bytes]]:
    """Messages that decode and type-check but whose meaning is poison, made from the run's own traffic that
    ``seen`` holds (the open bus lets anyone read it), plus payloads crafted against the decoder."""
    import dataclasses

    import numpy as np

    from ebrl.messages import (ActionChunk, Affinity, Observation, Quota, TrajectorySegment, Weights, WeightsPart,
                               decode_message)

    now = time.time()
    out: list[tuple[str, bytes]] = []
    if keys.traj(run, 0) in seen:
        seg = decode_message(TrajectorySegment, seen[keys.traj(run, 0)])
        out.append((keys.traj(run, 0), encode_message(dataclasses.replace(seg, rewards=np.full_like(seg.rewards, np.nan)))))
        out.append((keys.traj(run, 0), encode_message(dataclasses.replace(seg, logprobs=seg.logprobs[:-1]))))
        out.append((keys.traj(run, 0), encode_message(dataclasses.replace(seg, versions=seg.versions + 10**9))))
        # rewards finite but absurd (3e38, as no sim that clips at env.max_abs_reward sends): a NaN update once
        out.append((keys.traj(run, 0), encode_message(dataclasses.replace(seg, rewards=np.full_like(seg.rewards, 3e38)))))
    if keys.weights(run) in seen:
        real = decode_message(Weights, seen[keys.weights(run)])
        nan = {name: np.full_like(a, np.nan) if a.dtype.kind == "f" else a for name, a in real.params.items()}
        out.append((keys.weights(run), encode_message(dataclasses.replace(real, version=10**9, created_at=now))))
        # the trainer's own tensors numbered plausibly ahead: generation ahead of training stalled a run for good once
        out.append((keys.weights(run), encode_message(dataclasses.replace(real, version=real.version + 60, created_at=now))))
        out.append((keys.weights(run), encode_message(Weights(version=real.version + 1, params=nan, created_at=now))))
    out.append((keys.weights_parts(run), encode_message(WeightsPart(
        version=1, index=0, count=1 << 18, part_bytes=4 << 20, total_bytes=1 << 40, created_at=now,
        data=np.zeros(4 << 20, np.uint8)))))
    if keys.obs(run, 0) in seen:
        obs = decode_message(Observation, seen[keys.obs(run, 0)])
        out.append((keys.obs(run, 0), encode_message(dataclasses.replace(obs, env_ids=obs.env_ids[:-1]))))
        for group in range(1000, 1064):  # observations of groups the run does not have
            out.append((keys.obs(run, group), encode_message(dataclasses.replace(obs, group=group, seq=10**6))))
    act = ActionChunk(group=0, seq=0, policy_version=0, actions=np.full((4, 8, 1), np.nan, np.float32),
                      logprobs=np.zeros(4, np.float32), values=np.zeros(4, np.float32), latents=np.zeros((4, 0), np.float32))
    out.append((keys.act(run, 0), encode_message(act)))
    out.append((keys.act(run, 0), encode_message(dataclasses.replace(act, actions=np.zeros((4, 3, 7), np.float32)))))
    for role in ("sim", "gen", "train"):
        out.append((keys.ctl(run, role, 0, "quota"), encode_message(Quota(version=1, threads=0))))
        out.append((keys.ctl(run, role, 0, "affinity"), encode_message(Affinity(version=10**9, cores=[]))))
        out.append((keys.ctl(run, role, 0, "stop"), b"\x81\xa6reason\xc0"))  # a stop that is not one
    # a forged report of the one real trainer: a version no training reaches this fast would end the run
    out.append((keys.stats(run, "train", 0), encode_message(StatsReport(
        run=run, service="train", instance=0, time=now, seq=0,
        metrics={"train/policy_version": 10.0**6, "train/iteration": 10.0**6}))))
    out.append((keys.stats(run, "train", 0), encode_message(StatsReport(
        run=run, service="train", instance=0, time=now, seq=0, metrics={"train/policy_version": float("nan")}))))
    # against the decoder: a msgpack array header claiming 2**32 - 1 items, a map claiming as many, deep nesting
    for key in (keys.traj(run, 0), keys.obs(run, 0), keys.act(run, 0), keys.weights(run), keys.stats(run, "sim", 0)):
        out.extend([(key, b"\xdd\xff\xff\xff\xff" + b"\x00" * 64), (key, b"\xdf\xff\xff\xff\xff"),
                    (key, b"\x91" * 100_000)])
    return out


MARK_SEQ = 987_654_321  # the seq of every forged report
MARK_TIME = 12_345.0  # the created_at of every forged weights message
MARK_REASON = "insider stop"


def insider_attacks(run: str, run_dir: str, role: str) -> list[tuple[str, bytes]]:
    """What an insider signed in as ``role`` sends: what other roles own, each message plausible."""
    import numpy as np

    from ebrl import config as config_mod
    from ebrl.envs import EnvSpec, describe
    from ebrl import codec
    from ebrl.messages import Affinity, EpisodeBatch, GpuShare, Quota, to_wire
    from ebrl.policies import make_policy

    cfg = config_mod.load(os.path.join(run_dir, "config.toml"))
    info = describe(EnvSpec.from_config(cfg.env))
    params = {name: np.zeros(tuple(t.shape), np.float32)
              for name, t in make_policy(cfg.policy, info.layout, info.action_dim).state_dict().items()}
    out = [(keys.weights(run), encode_message(Weights(version=v, params=params, created_at=MARK_TIME)))
           for v in range(1, 121, 3)]  # the policy's own tensors, zeroed: some version is always just ahead
    huge = 1 << 53
    forged_return = {"train/policy_version": 2.0, "train/iteration": 2.0, "train/episode_return_mean": 1e9,
                     "train/success_rate": 1.0, "train/episodes": 1e6}
    out.append((keys.stats(run, "train", 0), encode_message(StatsReport(
        run=run, service="train", instance=0, time=time.time(), seq=mark(role), metrics=forged_return))))
    sim_return = {"sim/episode_return_mean": 1e9, "sim/success_rate": 1.0, "sim/env_steps": 10.0}
    for instance in (0, 1):  # the one simulator host, and one the run does not have
        out.append((keys.stats(run, "sim", instance), encode_message(StatsReport(
            run=run, service="sim", instance=instance, time=time.time(), seq=mark(role), metrics=sim_return))))
    out.append((keys.episodes(run, "sim"), encode_message(EpisodeBatch(
        service="sim", instance=0, env_id=[0], episode=[mark(role)], returns=[1e9], length=[1], success=[True],
        policy_version=[1], env_steps=[1], end_time=[time.time()]))))
    for stage in ("sim", "gen", "train"):
        out.append((keys.ctl(run, stage, 0, "quota"), encode_message(Quota(version=huge, threads=1, batch=1))))
        out.append((keys.ctl(run, stage, 0, "affinity"), encode_message(Affinity(version=huge, cores=[0]))))
    share = GpuShare(version=huge, stage="gen", env={"CUDA_VISIBLE_DEVICES": "0"})
    injected = {**to_wire(share), "env": {"CUDA_INJECTION64_PATH": "/tmp/inject.so"}}  # what GpuShare refuses
    out += [(keys.gpu_share(run, 0), encode_message(share)), (keys.gpu_share(run, 0), codec.encode(injected))]
    for stage in ("sim", "gen", "train", "log", "launcher"):
        out.append((keys.ctl(run, stage, 0, "stop"), encode_message(Stop(reason=MARK_REASON))))
    return out


def mark(role: str) -> int:
    """The seq of the reports an insider of ``role`` forges."""
    return MARK_SEQ + sorted(auth.IDENTITIES).index(role)


OTHERS = range(1, 64)  # the instances of its own role an insider also claims to be (the run has instance 0)


def other_instances(run: str, role: str) -> list[tuple[str, bytes]]:
    """Reports of the instances :data:`OTHERS` of ``role``, marked: a simulator's claim a billion env steps and
    a return no run reaches (the launcher would count them, were they the run's)."""
    metrics = ({"sim/env_steps": 1e9, "sim/env_steps_per_s": 1e6, "sim/episode_return_mean": 1e9,
                "sim/success_rate": 1.0} if role == "sim" else {f"{role}/policy_version": 1e6})
    return [(keys.stats(run, role, n), encode_message(StatsReport(run=run, service=role, instance=n, time=time.time(),
                                                                  seq=mark(role), metrics=metrics))) for n in OTHERS]


def main_insider(who: str, endpoint: str, run: str, run_dir: str, claims_only: bool = False) -> int:
    """Send :func:`insider_attacks` and :func:`other_instances` signed in as ``who`` (``ROLE/N``: that
    instance's own line; ``ROLE``: the role's line of the secret) until standard input closes, holding the
    tokens of a second trainer and of :data:`OTHERS` of its role; print what it sent and received, and how many
    sessions it had (it must have signed in: the test checks). ``claims_only``: only the claims to be
    :data:`OTHERS` (their tokens and reports), nothing that another role owns (a mesh takes that from any
    service: ``bus.mode = "peer"`` trusts them)."""
    role, _, instance = who.partition("/")
    secret = os.path.join(run_dir, auth.FILENAME)
    identity = auth.instance_line(secret, role, int(instance)) if instance else ""  # as its launcher hands it
    session = zenoh.open(zenoh_config(BusOptions(mode="client", connect=[endpoint], listen=[], secret_file=secret,
                                                 role=role, identity=identity)))
    received: dict[str, int] = {}

    def on_sample(sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        received[key] = received.get(key, 0) + 1

    session.declare_subscriber("ebrl/**", on_sample)  # more than the role may read: dropped where it enters
    claimed = ([] if claims_only else [keys.live(run, "train", 7)]) + [keys.live(run, role, n) for n in OTHERS]
    tokens = [session.liveliness().declare_token(key) for key in claimed]
    batch = ([] if claims_only else insider_attacks(run, run_dir, role)) + other_instances(run, role)
    done = threading.Event()
    threading.Thread(target=lambda: (sys.stdin.read(), done.set()), daemon=True).start()
    sent, routers, peers = 0, 0, 0
    while not done.is_set():
        routers = max(routers, len(list(session.info.routers_zid())))
        peers = max(peers, len(list(session.info.peers_zid())))
        for key, payload in batch:
            session.put(key, payload)
            sent += 1
        done.wait(0.1)
    del tokens
    print(json.dumps({"sent": sent, "kinds": len(batch), "routers": routers, "peers": peers, "received": received,
                      "own": sorted({key for key, _ in batch}), "tokens": claimed,
                      "user": identity.partition(":")[0] or auth.load(secret, role).user}), flush=True)
    os._exit(0)


def main() -> int:
    if sys.argv[1] == "--crafted":
        return main_crafted(*sys.argv[2:5])
    if sys.argv[1] in ("--insider", "--claims"):
        return main_insider(*sys.argv[2:6], claims_only=sys.argv[1] == "--claims")
    endpoint, run, run_dir = sys.argv[1:4]
    secret = os.path.join(run_dir, auth.FILENAME)
    try:
        with open(secret):
            readable = True
    except OSError:
        readable = False
    run_files = []  # what of the run's directory it could list or read (another user: nothing)
    for name in ("config.toml", "bus.json", "logs"):
        try:
            path = os.path.join(run_dir, name)
            os.listdir(path) if name == "logs" else open(path).close()
            run_files.append(name)
        except OSError:
            pass
    options = BusOptions(mode="peer", connect=[endpoint], listen=["tcp/127.0.0.1:0"])
    received: dict[str, int] = {}

    def on_sample(sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        received[key] = received.get(key, 0) + 1

    session = zenoh.open(zenoh_config(options))
    session.declare_subscriber("ebrl/**", on_sample)
    live = []
    session.liveliness().declare_subscriber("ebrl/live/**", lambda s: live.append(str(s.key_expr)), history=True)
    token = session.liveliness().declare_token(keys.live(run, "train", 7))  # would look like a second trainer
    done = threading.Event()
    threading.Thread(target=lambda: (sys.stdin.read(), done.set()), daemon=True).start()  # EOF: the run ended
    sent = 0
    peers = 0
    big = os.urandom(8 << 20)
    while not done.is_set():
        peers = max(peers, len(list(session.info.peers_zid())))
        for key, payload in attacks(run):
            session.put(key, payload)
            sent += 1
        session.put(keys.traj(run, 1), big)  # 8 MB of garbage on a data key
        done.wait(0.05)
    del token
    own = sorted({key for key, _ in attacks(run)} | {keys.traj(run, 1)})
    print(json.dumps({"secret_readable": readable, "run_files": run_files, "peers": peers, "received": received, "own": own, "sent": sent,
                      "liveliness": sorted(set(live)), "uid": os.getuid()}), flush=True)
    os._exit(0)  # zenoh's threads would hold interpreter exit


def main_crafted(endpoint: str, run: str, seconds: str) -> int:
    """On an open bus (bus.auth = false): read the run's traffic, then send crafted payloads on every key for
    ``seconds`` seconds (a batch every 0.1 s) and 8 MB of garbage on the data keys (every second); print what
    it sent."""
    session = zenoh.open(zenoh_config(BusOptions(mode="client", connect=[endpoint], listen=[])))  # as services join
    seen: dict[str, bytes] = {}

    def on_sample(sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        if key not in seen and len(seen) < 64:
            seen[key] = sample.payload.to_bytes()

    session.declare_subscriber("ebrl/data/**", on_sample)
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and not all(
            k in seen for k in (keys.traj(run, 0), keys.weights(run), keys.obs(run, 0))):
        time.sleep(0.05)
    batch = crafted(run, seen)
    big = os.urandom(8 << 20)
    sent, rounds, end = 0, 0, time.monotonic() + float(seconds)
    while time.monotonic() < end:
        for key, payload in batch:
            session.put(key, payload)
            sent += 1
        if rounds % 10 == 0:  # 8 MB of garbage on each data key once a second
            for key in (keys.traj(run, 1), keys.obs(run, 1), keys.weights(run)):
                session.put(key, big)
                sent += 1
        rounds += 1
        time.sleep(0.1)
    print(json.dumps({"sent": sent, "kinds": len(batch), "seen": sorted(seen)}), flush=True)
    os._exit(0)


if __name__ == "__main__":
    sys.exit(main())
