"""Stable-Baselines3's SAC with rl-zoo3's published hyperparameters: the off-policy peer EBRL's SAC races (issue 53).

    pip install stable-baselines3==2.9.2      # a benchmark dependency, not one of EBRL's
    python benchmarks/peers/sb3_sac.py --env Pendulum-v1 --seed 0 --json /tmp/sb3_sac_pendulum_s0.json
    python benchmarks/peers/sb3_sac.py --env HalfCheetah-v5 --total-steps 100000 --seed 0

One process, one env, SB3's loop as rl-zoo3 runs it: an env step, then ``gradient_steps`` updates
(``train_freq = 1``), the two strictly in turn. The hyperparameters are rl-zoo3's ``hyperparams/sac.yml`` for the
task (:data:`ZOO`; anything the file does not set is SB3's default: a replay of 1e6, batch 256, tau 0.005, gamma
0.99, automatic entropy, 2 x 256 ReLU MLPs); for HalfCheetah-v5 the file's MuJoCo defaults (written for v3).
The wall clock starts at the top of the script, so imports and the env's start count, as for EBRL's whole command.

Records, per finished episode, the env steps and wall seconds so far and the mean return of the last 20 episodes
(EBRL's ``train/episode_return_mean`` window), and at the end the final mean return and the seconds to the first
time the mean reached ``--target-return`` (if given). ``--json`` writes it all.
"""

from __future__ import annotations

import time

STARTED = time.time()  # before the imports: the whole command, as EBRL's is timed

import argparse  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import sys  # noqa: E402
from collections import deque  # noqa: E402
from typing import Any  # noqa: E402

WINDOW = 20  # episodes in the mean return, as EBRL's train/episode_return_mean

# rl-zoo3 hyperparams/sac.yml (DLR-RM/rl-baselines3-zoo): what the file sets for each task
ZOO: dict[str, dict[str, Any]] = {
    "Pendulum-v1": {"n_timesteps": 20_000, "learning_rate": 1e-3},
    "HalfCheetah-v5": {"n_timesteps": 1_000_000, "learning_starts": 10_000},  # &mujoco-defaults (HalfCheetah-v3)
}


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--env", default="Pendulum-v1", choices=sorted(ZOO))
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--total-steps", type=int, default=0, help="env steps (0: rl-zoo3's n_timesteps)")
    p.add_argument("--target-return", type=float, default=None, help="record when the mean return first reaches it")
    p.add_argument("--torch-threads", type=int, default=0, help="0: torch's default")
    p.add_argument("--json", default=None, help="write the summary and the curve here")
    return p.parse_args(argv)


def main(argv: list[str] | None = None) -> dict[str, Any]:
    args = parse_args(argv)
    import gymnasium as gym
    import stable_baselines3
    import torch
    from stable_baselines3 import SAC
    from stable_baselines3.common.callbacks import BaseCallback

    if args.torch_threads:
        torch.set_num_threads(args.torch_threads)
    zoo = dict(ZOO[args.env])
    total = args.total_steps or int(zoo.pop("n_timesteps"))
    zoo.pop("n_timesteps", None)
    env = gym.make(args.env)
    model = SAC("MlpPolicy", env, seed=args.seed, verbose=0, device="cpu", **zoo)
    returns: deque[float] = deque(maxlen=WINDOW)
    curve: list[dict[str, float]] = []
    reached: dict[str, float] = {}

    class Record(BaseCallback):
        """Each finished episode (SB3's Monitor fills ``infos[...]["episode"]``): the window's mean return."""

        def _on_step(self) -> bool:
            for info in self.locals.get("infos", []):
                if "episode" in info:
                    returns.append(float(info["episode"]["r"]))
                    mean = sum(returns) / len(returns)
                    row = {"env_steps": float(self.num_timesteps), "seconds": time.time() - STARTED,
                           "return_mean": mean, "episodes": float(len(curve) + 1)}
                    curve.append(row)
                    if args.target_return is not None and not reached and len(returns) == WINDOW \
                            and mean >= args.target_return:
                        reached.update(env_steps=row["env_steps"], seconds=row["seconds"])
            return True

    learn_start = time.time()
    model.learn(total_timesteps=total, callback=Record())
    wall = time.time() - STARTED
    summary = {
        "peer": "Stable-Baselines3 SAC, rl-zoo3 hyperparameters", "env": args.env, "seed": args.seed,
        "hyperparameters": {**ZOO[args.env], "total_steps": total}, "command": " ".join(["python", *sys.argv]),
        "versions": {"stable_baselines3": stable_baselines3.__version__, "torch": torch.__version__,
                     "gymnasium": gym.__version__, "python": platform.python_version()},
        "env_steps": total, "wall_s": round(wall, 2), "learn_s": round(time.time() - learn_start, 2),
        "final_return_mean": curve[-1]["return_mean"] if curve else None, "episodes": len(curve),
        "target_return": args.target_return, "target_reached": reached or None, "curve": curve,
    }
    print(f"{args.env} seed {args.seed}: {total} env steps in {wall:.1f} s; mean return of the last {WINDOW} "
          f"episodes {summary['final_return_mean']}")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(summary, fh, indent=1)
    return summary


if __name__ == "__main__":
    main()
