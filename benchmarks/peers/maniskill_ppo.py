"""GPU peer for EBRL's ManiSkill runs: CleanRL-style PPO on ManiSkill's GPU-vectorized environment, in one process.

    python benchmarks/peers/maniskill_ppo.py --env PickCube-v1 --num-envs 512 --target-success 0.9 \
        --max-seconds 900 --seed 0 --json benchmarks/results/peer_maniskill_ppo_pickcube.json

This is the loop ManiSkill's own PPO baseline runs (``examples/baselines/ppo/ppo.py``, itself CleanRL's
``ppo_continuous_action.py`` moved onto the GPU): one process; ``--num-envs`` environments in one ManiSkill
batch on GPU PhysX; ``--num-steps`` batched steps with every tensor on the GPU; then epochs of minibatch
updates while the simulator waits. Its defaults are that baseline's: 512 envs, 50 steps per rollout,
gamma 0.8, lambda 0.9, 4 epochs of 32 minibatches, target KL 0.1, learning rate 3e-4, tanh MLPs of 3 x 256
for actor and critic, log-std starting at -0.5, ``pd_joint_delta_pos`` control, the normalized dense reward.

What EBRL's side (``configs/maniskill.toml``) is matched on, for a fair race: the task, the number of
environments, the reward, the control mode, gamma and lambda, the episode limit; ``--hidden`` sets the network
(EBRL's ``policy.hidden``). As in ManiSkill's baseline, episodes that end are reset in the same step (partial
resets: ``reset(options={"env_idx": ...})``), and a time-limit truncation bootstraps from the value of the
final observation; a success ends the episode without a bootstrap.

Stop rule: the success rate of the last 20 finished episodes (over all envs) reaches ``--target-success``,
exactly EBRL's ``sim/success_rate`` and ``run.target_success``; or ``--max-seconds`` pass; or
``--total-timesteps`` are spent. Wall clock counts from the start of this script, before torch and ManiSkill
are imported (EBRL's counts from launch).
"""

from __future__ import annotations

import time

T0 = time.monotonic()  # before the heavy imports: everything after this is charged to the peer

import argparse  # noqa: E402
import collections  # noqa: E402
import json  # noqa: E402
import os  # noqa: E402
import platform  # noqa: E402
import random  # noqa: E402
import shlex  # noqa: E402
import sys  # noqa: E402
from dataclasses import asdict, dataclass  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402
from torch import nn  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from cleanrl_ppo import Agent  # noqa: E402  the same actor-critic, orthogonal init, tanh MLPs

WINDOW = 20  # episodes in the success rate and mean return, as EBRL's sim/success_rate


@dataclass
class Args:
    env: str = "PickCube-v1"
    num_envs: int = 512
    seed: int = 0
    target_success: float | None = 0.9
    max_seconds: float = 900.0
    json: str | None = None
    sim_backend: str = "physx_cuda"
    max_episode_steps: int = 50
    hidden: str = "256,256,256"
    init_log_std: float = -0.5
    # ManiSkill's examples/baselines/ppo/ppo.py defaults
    total_timesteps: int = 10_000_000
    learning_rate: float = 3e-4
    num_steps: int = 50
    gamma: float = 0.8
    gae_lambda: float = 0.9
    num_minibatches: int = 32
    update_epochs: int = 4
    clip_coef: float = 0.2
    ent_coef: float = 0.0
    vf_coef: float = 0.5
    max_grad_norm: float = 0.5
    target_kl: float | None = 0.1

    @property
    def batch_size(self) -> int:
        return self.num_envs * self.num_steps

    @property
    def minibatch_size(self) -> int:
        return self.batch_size // self.num_minibatches

    @property
    def num_iterations(self) -> int:
        return self.total_timesteps // self.batch_size


def parse_args(argv: list[str] | None = None) -> Args:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    for name, default in asdict(Args()).items():
        flag = "--" + name.replace("_", "-")
        if name in ("target_success", "target_kl"):
            p.add_argument(flag, type=lambda t: None if t.lower() == "none" else float(t), default=default,
                           help="'none': off")
        elif name == "json":
            p.add_argument(flag, default=None, help="write the summary, hyper-parameters and curve here")
        else:
            p.add_argument(flag, type=type(default), default=default, help="default: %(default)s")
    return Args(**vars(p.parse_args(argv)))


def make_envs(args: Args) -> Any:
    """ManiSkill's batched environment: every input and output a [num_envs, ...] torch tensor on its device."""
    import gymnasium as gym
    import mani_skill.envs  # noqa: F401  registers the tasks

    return gym.make(args.env, num_envs=args.num_envs, obs_mode="state", control_mode="pd_joint_delta_pos",
                    reward_mode="normalized_dense", sim_backend=args.sim_backend,
                    max_episode_steps=args.max_episode_steps)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    command = " ".join(shlex.quote(a) for a in [sys.executable, *(sys.argv if argv is None else argv)])
    random.seed(args.seed)
    np.random.seed(args.seed)
    torch.manual_seed(args.seed)
    device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    hidden = [int(w) for w in args.hidden.split(",")]

    envs = make_envs(args)
    space = envs.unwrapped.single_action_space
    low = torch.as_tensor(space.low, device=device)
    high = torch.as_tensor(space.high, device=device)
    next_obs, _ = envs.reset(seed=args.seed)
    next_obs = torch.as_tensor(next_obs, device=device).float()
    n, obs_dim, act_dim = args.num_envs, next_obs.shape[1], int(np.prod(space.shape))

    agent = Agent(obs_dim, act_dim, hidden).to(device)
    with torch.no_grad():
        agent.actor_logstd.fill_(args.init_log_std)
    optimizer = torch.optim.Adam(agent.parameters(), lr=args.learning_rate, eps=1e-5)

    obs = torch.zeros((args.num_steps, n, obs_dim), device=device)
    actions = torch.zeros((args.num_steps, n, act_dim), device=device)
    logprobs, rewards, dones, values, final_values = (torch.zeros((args.num_steps, n), device=device)
                                                      for _ in range(5))
    ep_return = torch.zeros(n, device=device)
    ep_success = torch.zeros(n, dtype=torch.bool, device=device)
    returns_window: collections.deque[float] = collections.deque(maxlen=WINDOW)
    success_window: collections.deque[bool] = collections.deque(maxlen=WINDOW)
    curve: list[dict[str, Any]] = []
    episodes = global_step = updates = 0
    rollout_s = update_s = 0.0
    reached: dict[str, Any] | None = None
    stop_reason = "total_timesteps"
    next_done = torch.zeros(n, device=device)
    t_envs_ready = time.monotonic() - T0
    print(f"[{t_envs_ready:7.1f} s] {n} x {args.env} ready on {device}; batch {args.batch_size}, "
          f"minibatch {args.minibatch_size}", flush=True)

    def rate() -> float | None:
        return float(np.mean(success_window)) if success_window else None

    for _iteration in range(1, args.num_iterations + 1):
        # ---- rollout: num_steps batched steps, partial resets of the envs whose episode ended ----
        t_phase = time.monotonic()
        final_values.zero_()
        for step in range(args.num_steps):
            global_step += n
            obs[step] = next_obs
            dones[step] = next_done
            with torch.no_grad():
                action, logprob, _, value = agent.get_action_and_value(next_obs)
                values[step] = value.flatten()
            actions[step] = action
            logprobs[step] = logprob
            raw, reward, terminated, truncated, info = envs.step(torch.clamp(action, low, high))
            next_obs = torch.as_tensor(raw, device=device).float()
            reward = torch.as_tensor(reward, device=device).float().view(-1)
            terminated = torch.as_tensor(terminated, device=device).view(-1).bool()
            truncated = torch.as_tensor(truncated, device=device).view(-1).bool()
            rewards[step] = reward
            ep_return += reward
            if "success" in info:
                ep_success |= torch.as_tensor(info["success"], device=device).view(-1).bool()
            done = terminated | truncated
            next_done = done.float()
            if bool(done.any()):
                idx = torch.nonzero(done).view(-1)
                cut = torch.nonzero(truncated & ~terminated).view(-1)
                if len(cut):  # a time limit, not an outcome: bootstrap from the final observation's value
                    with torch.no_grad():
                        final_values[step, cut] = agent.get_value(next_obs[cut]).view(-1)
                returns_window.extend(ep_return[idx].tolist())
                success_window.extend(ep_success[idx].tolist())
                episodes += len(idx)
                ep_return[idx] = 0.0
                ep_success[idx] = False
                raw, _ = envs.reset(options={"env_idx": idx})
                next_obs = torch.as_tensor(raw, device=device).float()
                success = rate()
                if args.target_success is not None and success is not None and len(success_window) == WINDOW \
                        and success >= args.target_success:
                    reached = {"wall_s": time.monotonic() - T0, "env_steps": global_step, "updates": updates,
                               "success_rate": success, "return": float(np.mean(returns_window))}
                    break
            if time.monotonic() - T0 >= args.max_seconds:
                break
        rollout_s += time.monotonic() - t_phase
        if reached is not None:
            stop_reason = "target_success"
            break
        if time.monotonic() - T0 >= args.max_seconds:
            stop_reason = "max_seconds"
            break

        # ---- GAE: dones[t] marks the first step of a new episode; truncations bootstrap ----
        t_phase = time.monotonic()
        with torch.no_grad():
            next_value = agent.get_value(next_obs).reshape(-1)
            advantages = torch.zeros_like(rewards)
            lastgaelam = torch.zeros(n, device=device)
            for t in reversed(range(args.num_steps)):
                not_done = 1.0 - (next_done if t == args.num_steps - 1 else dones[t + 1])
                next_values = next_value if t == args.num_steps - 1 else values[t + 1]
                delta = rewards[t] + args.gamma * (not_done * next_values + final_values[t]) - values[t]
                advantages[t] = lastgaelam = delta + args.gamma * args.gae_lambda * not_done * lastgaelam
            returns = advantages + values
        b_obs, b_actions = obs.reshape(-1, obs_dim), actions.reshape(-1, act_dim)
        b_logprobs, b_advantages, b_returns = logprobs.reshape(-1), advantages.reshape(-1), returns.reshape(-1)

        # ---- update: epochs x minibatches of clipped-surrogate PPO, stopped early past the target KL ----
        for _epoch in range(args.update_epochs):
            order = torch.randperm(args.batch_size, device=device)
            for start in range(0, args.batch_size, args.minibatch_size):
                mb = order[start:start + args.minibatch_size]
                _, newlogprob, entropy, newvalue = agent.get_action_and_value(b_obs[mb], b_actions[mb])
                logratio = newlogprob - b_logprobs[mb]
                ratio = logratio.exp()
                with torch.no_grad():
                    approx_kl = ((ratio - 1) - logratio).mean()
                adv = b_advantages[mb]
                adv = (adv - adv.mean()) / (adv.std() + 1e-8)
                pg_loss = torch.max(-adv * ratio, -adv * torch.clamp(ratio, 1 - args.clip_coef,
                                                                    1 + args.clip_coef)).mean()
                v_loss = 0.5 * ((newvalue.view(-1) - b_returns[mb]) ** 2).mean()
                loss = pg_loss - args.ent_coef * entropy.mean() + v_loss * args.vf_coef
                optimizer.zero_grad()
                loss.backward()
                nn.utils.clip_grad_norm_(agent.parameters(), args.max_grad_norm)
                optimizer.step()
            if args.target_kl is not None and float(approx_kl) > args.target_kl:
                break
        updates += 1
        update_s += time.monotonic() - t_phase
        now = time.monotonic() - T0
        success = rate()
        curve.append({"wall_s": round(now, 3), "env_steps": global_step, "updates": updates,
                      "success_rate": success, "return": float(np.mean(returns_window)) if returns_window else None})
        print(f"[{now:7.1f} s] update {updates:4d}  env steps {global_step:9d}  {global_step / now:8.0f} steps/s  "
              f"episodes {episodes:7d}  success (last {WINDOW}) {'-' if success is None else f'{success:.0%}'}",
              flush=True)
        if now >= args.max_seconds:
            stop_reason = "max_seconds"
            break

    wall_s = time.monotonic() - T0
    envs.close()
    summary = {
        "stop_reason": stop_reason, "wall_s": round(wall_s, 2), "env_start_s": round(t_envs_ready, 2),
        "env_steps": global_step, "env_steps_per_s": round(global_step / wall_s, 1), "updates": updates,
        "episodes": episodes, "rollout_s": round(rollout_s, 2), "update_s": round(update_s, 2),
        "final_success_rate": rate(), "target_success": args.target_success,
        "target_reached": None if reached is None else {k: round(v, 3) if isinstance(v, float) else v
                                                        for k, v in reached.items()},
    }
    if reached is not None:
        print(f"\nreached success {reached['success_rate']:.0%} after {reached['wall_s']:.1f} s wall clock "
              f"({reached['env_steps']} env steps, {reached['updates']} updates)")
    else:
        print(f"\ntarget success {args.target_success} not reached (stopped on {stop_reason})")
    if args.json:
        out = {
            "peer": "CleanRL-style PPO on ManiSkill's GPU-vectorized env, one process (as ManiSkill's PPO baseline)",
            "command": command, "device": str(device),
            "gpu": torch.cuda.get_device_name(0) if device.type == "cuda" else None,
            "machine": f"{platform.machine()}, {len(os.sched_getaffinity(0))} usable cores",
            "date": time.strftime("%Y-%m-%d"),
            "versions": {"python": platform.python_version(), "torch": torch.__version__},
            "summary": summary,
            "hyperparameters": {**asdict(args), "batch_size": args.batch_size, "minibatch_size": args.minibatch_size,
                                "action_chunk": 1},
            "curve": curve,
        }
        path = Path(args.json)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(out, indent=2) + "\n")
        print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
