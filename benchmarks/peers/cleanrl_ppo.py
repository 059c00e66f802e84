"""Outside peer for EBRL: a CleanRL-style PPO that you could write yourself, on the quickstart task.

    python benchmarks/peers/cleanrl_ppo.py --env InvertedPendulum-v5 --num-envs 8 \
        --target-return 900 --max-seconds 900 --seed 0 --json benchmarks/results/peer_cleanrl_ppo.json

This is a faithful transcription of CleanRL's ``ppo_continuous_action.py``
(https://github.com/vwxyzjn/cleanrl), ported to the installed gymnasium 1.x
vector API and with a stopping rule added. It is *not* tuned against EBRL: the
hyper-parameters are CleanRL's defaults, except the ones fixed to match EBRL's
quickstart (``configs/quickstart.toml``) or to answer the benchmark's question:

* same task (``InvertedPendulum-v5``), same number of envs (8), same policy size
  (tanh MLP, ``--hidden 64,64`` for actor and critic, EBRL's ``policy.hidden``);
* ``--num-steps 256``: with 8 envs this keeps CleanRL's default batch of 2048
  env steps and minibatch of 64 (32 minibatches);
* no action chunking: one action per observation, as a researcher's baseline;
* stop when the mean return of the last 20 finished episodes (over all envs)
  reaches ``--target-return``, exactly EBRL's ``sim/episode_return_mean`` /
  ``run.target_return``, or when ``--max-seconds`` pass, or after
  ``--total-timesteps`` (CleanRL's 1M, also the horizon of the lr annealing);
* ``torch.set_num_threads(1)`` (``--torch-threads``): the policy is tiny and 8
  env processes already share 2 cores; EBRL's gen and train services also use 1.

Like CleanRL, the loop is synchronous: ``--num-steps`` vector steps through a
``gymnasium.vector.AsyncVectorEnv`` (one process per env, stepped in lock-step),
then 10 epochs of updates while the envs wait. The per-env wrappers are
CleanRL's (ClipAction, NormalizeObservation, NormalizeReward and their clips);
``--no-normalize`` drops the two normalisations. Episode returns are read from a
``RecordEpisodeStatistics`` placed below the normalisations, so they are the
environment's raw returns, comparable to EBRL's.

gymnasium 1.x: the vector env is created with ``autoreset_mode=SAME_STEP``. The
default (NEXT_STEP) returns the terminal observation and resets on the *next*
``step()`` (ignoring that action and returning reward 0), which would put a fake
transition in every rollout; SAME_STEP resets inside the step that ends the
episode and returns the reset observation, the gym 0.26 behaviour CleanRL's GAE
(``dones[t + 1]`` cuts the bootstrap) was written for. The finished episode's
statistics then come in ``infos["final_info"]["episode"]`` with the mask
``infos["final_info"]["_episode"]``. As in CleanRL, time-limit truncation is
treated as termination (no bootstrap from the final observation).

Wall clock counts from the start of this script, before torch and gymnasium
are imported, so env start-up is included (EBRL's number counts from launch).
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

import gymnasium as gym  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
from torch import nn  # noqa: E402
from torch.distributions.normal import Normal  # noqa: E402

RETURN_WINDOW = 20  # episodes in the mean return, as EBRL's sim/episode_return_mean


@dataclass
class Args:
    env: str = "InvertedPendulum-v5"
    num_envs: int = 8
    seed: int = 0
    target_return: float | None = 900.0
    max_seconds: float = 900.0
    json: str | None = None
    torch_threads: int = 1
    hidden: str = "64,64"
    normalize: bool = True
    # CleanRL ppo_continuous_action.py defaults (num_steps: see the module docstring)
    total_timesteps: int = 1_000_000
    learning_rate: float = 3e-4
    num_steps: int = 256
    anneal_lr: bool = True
    gamma: float = 0.99
    gae_lambda: float = 0.95
    num_minibatches: int = 32
    update_epochs: int = 10
    norm_adv: bool = True
    clip_coef: float = 0.2
    clip_vloss: bool = True
    ent_coef: float = 0.0
    vf_coef: float = 0.5
    max_grad_norm: float = 0.5
    target_kl: float | None = None

    @property
    def batch_size(self) -> int:
        return self.num_envs * self.num_steps

    @property
    def minibatch_size(self) -> int:
        return self.batch_size // self.num_minibatches

    @property
    def num_iterations(self) -> int:
        return self.total_timesteps // self.batch_size


def _float_or_none(text: str) -> float | None:
    return None if text.lower() == "none" else float(text)


def parse_args() -> Args:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    for name, default in asdict(Args()).items():
        flag = "--" + name.replace("_", "-")
        if isinstance(default, bool):
            p.add_argument(flag, action=argparse.BooleanOptionalAction, default=default, help="default: %(default)s")
        elif name in ("target_return", "target_kl"):
            p.add_argument(flag, type=_float_or_none, default=default, help="'none': off")
        elif name == "json":
            p.add_argument(flag, default=None, help="write the summary, hyper-parameters and curve here")
        else:
            p.add_argument(flag, type=type(default), default=default, help="default: %(default)s")
    return Args(**vars(p.parse_args()))


def make_env(env_id: str, gamma: float, normalize: bool):
    def thunk() -> gym.Env:
        env = gym.make(env_id)
        env = gym.wrappers.FlattenObservation(env)
        env = gym.wrappers.RecordEpisodeStatistics(env)  # raw returns: below the normalisations
        env = gym.wrappers.ClipAction(env)
        if normalize:
            env = gym.wrappers.NormalizeObservation(env)
            env = gym.wrappers.TransformObservation(env, lambda obs: np.clip(obs, -10, 10), env.observation_space)
            env = gym.wrappers.NormalizeReward(env, gamma=gamma)
            env = gym.wrappers.TransformReward(env, lambda reward: np.clip(reward, -10, 10))
        return env

    return thunk


def layer_init(layer: nn.Linear, std: float = np.sqrt(2), bias_const: float = 0.0) -> nn.Linear:
    torch.nn.init.orthogonal_(layer.weight, std)
    torch.nn.init.constant_(layer.bias, bias_const)
    return layer


def mlp(n_in: int, hidden: list[int], n_out: int, out_std: float) -> nn.Sequential:
    layers: list[nn.Module] = []
    for width in hidden:
        layers += [layer_init(nn.Linear(n_in, width)), nn.Tanh()]
        n_in = width
    layers.append(layer_init(nn.Linear(n_in, n_out), std=out_std))
    return nn.Sequential(*layers)


class Agent(nn.Module):
    def __init__(self, obs_dim: int, act_dim: int, hidden: list[int]):
        super().__init__()
        self.critic = mlp(obs_dim, hidden, 1, out_std=1.0)
        self.actor_mean = mlp(obs_dim, hidden, act_dim, out_std=0.01)
        self.actor_logstd = nn.Parameter(torch.zeros(1, act_dim))

    def get_value(self, x: torch.Tensor) -> torch.Tensor:
        return self.critic(x)

    def get_action_and_value(self, x: torch.Tensor, action: torch.Tensor | None = None):
        action_mean = self.actor_mean(x)
        action_std = torch.exp(self.actor_logstd.expand_as(action_mean))
        probs = Normal(action_mean, action_std)
        if action is None:
            action = probs.sample()
        return action, probs.log_prob(action).sum(1), probs.entropy().sum(1), self.critic(x)


def main() -> int:
    args = parse_args()
    command = " ".join(shlex.quote(a) for a in [sys.executable, *sys.argv])
    random.seed(args.seed)
    np.random.seed(args.seed)
    torch.manual_seed(args.seed)
    torch.set_num_threads(args.torch_threads)
    hidden = [int(w) for w in args.hidden.split(",")]

    envs = gym.vector.AsyncVectorEnv(
        [make_env(args.env, args.gamma, args.normalize) for _ in range(args.num_envs)],
        autoreset_mode=gym.vector.AutoresetMode.SAME_STEP)
    assert isinstance(envs.single_action_space, gym.spaces.Box), "continuous actions only"
    obs_dim = int(np.prod(envs.single_observation_space.shape))
    act_dim = int(np.prod(envs.single_action_space.shape))

    agent = Agent(obs_dim, act_dim, hidden)
    optimizer = torch.optim.Adam(agent.parameters(), lr=args.learning_rate, eps=1e-5)

    obs = torch.zeros((args.num_steps, args.num_envs, obs_dim))
    actions = torch.zeros((args.num_steps, args.num_envs, act_dim))
    logprobs = torch.zeros((args.num_steps, args.num_envs))
    rewards = torch.zeros((args.num_steps, args.num_envs))
    dones = torch.zeros((args.num_steps, args.num_envs))
    values = torch.zeros((args.num_steps, args.num_envs))

    returns_window: collections.deque[float] = collections.deque(maxlen=RETURN_WINDOW)
    curve: list[dict[str, float]] = []
    episodes, global_step, updates = 0, 0, 0
    rollout_s = update_s = 0.0  # wall time in the two phases (the envs are idle during updates)
    reached: dict[str, float] | None = None
    stop_reason = "total_timesteps"

    def mean_return() -> float | None:
        return float(np.mean(returns_window)) if returns_window else None

    next_obs, _ = envs.reset(seed=args.seed)
    envs.single_action_space.seed(args.seed)
    next_obs = torch.Tensor(next_obs)
    next_done = torch.zeros(args.num_envs)
    t_envs_ready = time.monotonic() - T0
    print(f"[{t_envs_ready:7.1f} s] {args.num_envs} x {args.env} ready; batch {args.batch_size}, "
          f"minibatch {args.minibatch_size}, torch threads {torch.get_num_threads()}", flush=True)

    for iteration in range(1, args.num_iterations + 1):
        if args.anneal_lr:
            frac = 1.0 - (iteration - 1.0) / args.num_iterations
            optimizer.param_groups[0]["lr"] = frac * args.learning_rate

        # ---- rollout: num_steps synchronous vector steps ----
        t_phase = time.monotonic()
        for step in range(args.num_steps):
            global_step += args.num_envs
            obs[step] = next_obs
            dones[step] = next_done
            with torch.no_grad():
                action, logprob, _, value = agent.get_action_and_value(next_obs)
                values[step] = value.flatten()
            actions[step] = action
            logprobs[step] = logprob

            next_obs_np, reward, terminations, truncations, infos = envs.step(action.numpy())
            next_done = torch.Tensor(np.logical_or(terminations, truncations))
            rewards[step] = torch.as_tensor(reward, dtype=torch.float32).view(-1)
            next_obs = torch.Tensor(next_obs_np)

            if "final_info" in infos:  # SAME_STEP: stats of the episodes that ended in this step
                final = infos["final_info"]
                for i in np.flatnonzero(final.get("_episode", [])):
                    returns_window.append(float(final["episode"]["r"][i]))
                    episodes += 1
                ret = mean_return()
                if args.target_return is not None and ret is not None and ret >= args.target_return:
                    reached = {"wall_s": time.monotonic() - T0, "env_steps": global_step,
                               "updates": updates, "return": ret}
                    break
            if time.monotonic() - T0 >= args.max_seconds:
                break
        rollout_s += time.monotonic() - t_phase
        if reached is not None:
            stop_reason = "target_return"
            break
        if time.monotonic() - T0 >= args.max_seconds:
            stop_reason = "max_seconds"
            break

        t_phase = time.monotonic()
        # ---- GAE (CleanRL: done flags mark the first step of a new episode) ----
        with torch.no_grad():
            next_value = agent.get_value(next_obs).reshape(1, -1)
            advantages = torch.zeros_like(rewards)
            lastgaelam = 0
            for t in reversed(range(args.num_steps)):
                if t == args.num_steps - 1:
                    nextnonterminal = 1.0 - next_done
                    nextvalues = next_value
                else:
                    nextnonterminal = 1.0 - dones[t + 1]
                    nextvalues = values[t + 1]
                delta = rewards[t] + args.gamma * nextvalues * nextnonterminal - values[t]
                advantages[t] = lastgaelam = delta + args.gamma * args.gae_lambda * nextnonterminal * lastgaelam
            returns = advantages + values

        b_obs = obs.reshape((-1, obs_dim))
        b_logprobs = logprobs.reshape(-1)
        b_actions = actions.reshape((-1, act_dim))
        b_advantages = advantages.reshape(-1)
        b_returns = returns.reshape(-1)
        b_values = values.reshape(-1)

        # ---- update: epochs x minibatches of clipped-surrogate PPO ----
        b_inds = np.arange(args.batch_size)
        for _epoch in range(args.update_epochs):
            np.random.shuffle(b_inds)
            for start in range(0, args.batch_size, args.minibatch_size):
                mb_inds = b_inds[start:start + args.minibatch_size]
                _, newlogprob, entropy, newvalue = agent.get_action_and_value(b_obs[mb_inds], b_actions[mb_inds])
                logratio = newlogprob - b_logprobs[mb_inds]
                ratio = logratio.exp()
                with torch.no_grad():
                    approx_kl = ((ratio - 1) - logratio).mean()

                mb_advantages = b_advantages[mb_inds]
                if args.norm_adv:
                    mb_advantages = (mb_advantages - mb_advantages.mean()) / (mb_advantages.std() + 1e-8)
                pg_loss1 = -mb_advantages * ratio
                pg_loss2 = -mb_advantages * torch.clamp(ratio, 1 - args.clip_coef, 1 + args.clip_coef)
                pg_loss = torch.max(pg_loss1, pg_loss2).mean()

                newvalue = newvalue.view(-1)
                if args.clip_vloss:
                    v_loss_unclipped = (newvalue - b_returns[mb_inds]) ** 2
                    v_clipped = b_values[mb_inds] + torch.clamp(newvalue - b_values[mb_inds],
                                                                -args.clip_coef, args.clip_coef)
                    v_loss_clipped = (v_clipped - b_returns[mb_inds]) ** 2
                    v_loss = 0.5 * torch.max(v_loss_unclipped, v_loss_clipped).mean()
                else:
                    v_loss = 0.5 * ((newvalue - b_returns[mb_inds]) ** 2).mean()

                loss = pg_loss - args.ent_coef * entropy.mean() + v_loss * args.vf_coef
                optimizer.zero_grad()
                loss.backward()
                nn.utils.clip_grad_norm_(agent.parameters(), args.max_grad_norm)
                optimizer.step()
            if args.target_kl is not None and approx_kl > args.target_kl:
                break
        updates += 1
        update_s += time.monotonic() - t_phase

        now = time.monotonic() - T0
        ret = mean_return()
        curve.append({"wall_s": round(now, 3), "env_steps": global_step, "updates": updates,
                      "return": ret})
        print(f"[{now:7.1f} s] update {updates:4d}  env steps {global_step:8d}  "
              f"{global_step / now:7.0f} steps/s  episodes {episodes:6d}  "
              f"return (last {RETURN_WINDOW}) {'-' if ret is None else f'{ret:.1f}'}", flush=True)
        if now >= args.max_seconds:
            stop_reason = "max_seconds"
            break

    wall_s = time.monotonic() - T0
    envs.close()
    final = mean_return()
    curve.append({"wall_s": round(wall_s, 3), "env_steps": global_step, "updates": updates, "return": final})
    summary = {
        "stop_reason": stop_reason,
        "wall_s": round(wall_s, 2),
        "env_start_s": round(t_envs_ready, 2),
        "env_steps": global_step,
        "env_steps_per_s": round(global_step / wall_s, 1),
        "updates": updates,
        "episodes": episodes,
        "rollout_s": round(rollout_s, 2),
        "update_s": round(update_s, 2),
        "final_return": None if final is None else round(final, 1),
        "target_return": args.target_return,
        "target_reached": None if reached is None else {k: round(v, 2) if isinstance(v, float) else v
                                                        for k, v in reached.items()},
    }
    hyper = {**asdict(args), "batch_size": args.batch_size, "minibatch_size": args.minibatch_size,
             "num_iterations": args.num_iterations, "action_chunk": 1,
             "autoreset_mode": "SameStep", "vector_env": "gymnasium.vector.AsyncVectorEnv"}

    print()
    if reached is not None:
        print(f"reached target return {args.target_return:g}: mean return {reached['return']:.1f} "
              f"after {reached['wall_s']:.1f} s wall clock ({reached['env_steps']} env steps, "
              f"{reached['updates']} updates)")
    else:
        print(f"target return {args.target_return} not reached (stopped on {stop_reason})")
    print(f"wall {wall_s:.1f} s (envs ready after {t_envs_ready:.1f} s), env steps {global_step}, "
          f"{global_step / wall_s:.0f} env steps/s, updates {updates}, episodes {episodes}, "
          f"final mean return (last {RETURN_WINDOW}) {'-' if final is None else f'{final:.1f}'}")
    print(f"time in rollout {rollout_s:.1f} s, in updates {update_s:.1f} s (envs idle)")

    if args.json:
        out = {
            "peer": "CleanRL-style PPO (ppo_continuous_action.py), synchronous rollout then update, no chunking",
            "command": command,
            "machine": f"{platform.machine()}, {len(os.sched_getaffinity(0))} usable cores",
            "date": time.strftime("%Y-%m-%d"),
            "versions": {"python": platform.python_version(), "torch": torch.__version__,
                         "gymnasium": gym.__version__, "numpy": np.__version__},
            "summary": summary,
            "hyperparameters": hyper,
            "curve": curve,
        }
        path = Path(args.json)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(out, indent=2) + "\n")
        print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
