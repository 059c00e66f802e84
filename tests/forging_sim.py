"""A simulator that forges its episodes' values: signed in with sim/0's own line (as its launcher hands it to the
simulator's process: a user's env code there, or the line leaked), it sends, until its standard input closes,
segments on its own group's key whose rewards are plausible and whose reported episodes are not what the rewards
make: the issue's case (a segment whose rewards sum to 44 listing 20 finished episodes of return 5000), one
episode of return 5000 claimed for 44, a segment that ended no episode claiming one, and replays of a consistent
episode. Each is well formed and within every bound a simulator's messages have, so only training's own
accounting can refuse it. Prints one JSON line of what it sent.

    python tests/forging_sim.py ENDPOINT RUN RUN_DIR
"""

from __future__ import annotations

import json
import os
import sys
import threading

import numpy as np
import zenoh

from ebrl import config as config_mod
from ebrl import keys
from ebrl.bus import auth
from ebrl.bus.session import BusOptions, zenoh_config
from ebrl.envs import EnvSpec, describe
from ebrl.messages import TrajectorySegment, encode_message

FORGED_RETURN = 5000.0  # past the quickstart's target (900) and past what InvertedPendulum can return (1000)


def forged_segments(cfg, info) -> list[TrajectorySegment]:
    """Segments of the run's shapes for its envs (group 0), each claiming what its rewards do not make."""
    k, t = cfg.policy.chunk, 11
    obs = np.zeros((t, *info.obs_shape), np.float32)

    def segment(env: int, episode: int, end: str, returns: list[float], lengths: list[int]) -> TrajectorySegment:
        return TrajectorySegment(
            group=0, env_id=env, episode=episode, obs=obs, actions=np.zeros((t, k, info.action_dim), np.float32),
            latents=np.zeros((t, 0), np.float32), logprobs=np.zeros(t, np.float32), values=np.zeros(t, np.float32),
            rewards=np.full(t, 4.0, np.float32), steps=np.full(t, k, np.int32), versions=np.zeros(t, np.int64),
            end=end, last_obs=obs[0], episode_returns=returns, episode_lengths=lengths,  # type: ignore[arg-type]
            episode_successes=[True] * len(returns), episode_offset=0)

    n = t * k  # env steps; the rewards sum to 44
    envs = range(cfg.sim.envs_per_group)
    return ([segment(env, 10**6, "terminated", [FORGED_RETURN] * 20, [n] * 20) for env in envs]  # the case
            + [segment(env, 10**6 + 1, "terminated", [FORGED_RETURN], [n]) for env in envs]  # 5000 claimed for 44
            + [segment(env, 10**6 + 2, "cut", [FORGED_RETURN], [n]) for env in envs]  # no end, yet an episode
            + [segment(0, 10**6 + 3, "terminated", [44.0], [n])] * 4)  # a consistent episode, then its replays


def main(endpoint: str, run: str, run_dir: str) -> int:
    cfg = config_mod.load(os.path.join(run_dir, "config.toml"))
    info = describe(EnvSpec.from_config(cfg.env))
    secret = os.path.join(run_dir, auth.FILENAME)
    session = zenoh.open(zenoh_config(BusOptions(mode="client", connect=[endpoint], listen=[], role="sim",
                                                 identity=auth.instance_line(secret, "sim", 0))))
    batch = [encode_message(seg) for seg in forged_segments(cfg, info)]
    done = threading.Event()
    threading.Thread(target=lambda: (sys.stdin.read(), done.set()), daemon=True).start()
    sent, routers = 0, 0
    while not done.is_set():
        routers = max(routers, len(list(session.info.routers_zid())))
        for payload in batch:
            session.put(keys.traj(run, 0), payload)
            sent += 1
        done.wait(0.2)
    print(json.dumps({"sent": sent, "kinds": len(batch), "routers": routers}), flush=True)
    os._exit(0)  # zenoh's threads would hold interpreter exit


if __name__ == "__main__":
    sys.exit(main(*sys.argv[1:4]))
