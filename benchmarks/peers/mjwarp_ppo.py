"""GPU peer for EBRL's MuJoCo Warp runs: one-process PPO on the same MuJoCo Warp batch, every tensor on its device.

    python benchmarks/peers/mjwarp_ppo.py --num-envs 2048 --target-success 0.9 --max-seconds 900 --seed 0 \\
        --json benchmarks/results/peer_mjwarp_ppo_pickcube.json

    # a smoke test on Warp's CPU device (the first run compiles MuJoCo Warp's kernels: 10-60 s, cached after)
    python benchmarks/peers/mjwarp_ppo.py --device cpu --num-envs 16 --max-seconds 60 --torch-threads 1

What it is. The loop that users of GPU simulators write for themselves, in the shape of ManiSkill's
``examples/baselines/ppo/ppo.py`` (CleanRL's ``ppo_continuous_action.py`` moved onto the GPU) and of MuJoCo
Playground's Brax PPO: one process; ``--num-envs`` worlds of ``PandaPickCube-v0`` in one MuJoCo Warp model
(EBRL's own :class:`~ebrl.envs.batch.MjWarpBatch`, so both sides step the very same physics, reward and
observation code, one CUDA graph per env step); a rollout of ``--num-steps`` batched steps with the policy's
forward pass, the sampling and the storage on the same device as the worlds; then epochs of minibatch updates
while the simulator waits. Nothing travels to the host but the per-step "did any episode end" check (which
ManiSkill's loop has too) and the indices of the worlds to reset.

Why it is a faithful baseline, not a straw man:

* the same task, worlds and budget as EBRL's side (``configs/mjwarp_pickcube.toml``): 2048 worlds (EBRL's 2
  groups of 1024), 32 env steps of every world per update (EBRL's 16384 decisions of 4 steps), 600 updates
  (~39M env steps), the same 90 % success stop rule over the last 20 finished episodes (``run.target_success``,
  EBRL's ``sim/success_rate``); world ``i`` is seeded ``seed * 100003 + i`` as EBRL seeds env ``i``;
* the same network and hyper-parameters: tanh MLPs of 3 x 256 for actor and critic (orthogonal init, actor
  output gain 0.01), a learned state-independent log-std starting at -0.5, observations standardised by a
  running mean and variance (Chan et al.'s parallel update, clipped at +-10, folded in from each rollout
  before its gradient steps, exactly as EBRL's ``policy.normalize_obs``), gamma 0.97, lambda 0.95, clip 0.2,
  4 epochs of 8 minibatches (the same 32 gradient steps per update), Adam at 3e-4 (eps 1e-5), value
  coefficient 0.5, no entropy bonus, gradient norm clipped at 0.5, advantages normalised per minibatch;
* the textbook details ManiSkill's loop gets right: partial resets (a world whose episode ended, by a fall
  or the 100-step limit, starts its next episode in the same step, with its episode counter
  incremented, through ``batch.reset(idx, episodes)``); GAE that bootstraps a time-limit truncation from the
  value of the final observation (ManiSkill's ``final_values``) and a termination from nothing;
* it acts every env step (no action chunks: a researcher's own baseline would not chunk), which gives it
  finer control than EBRL's 4-step chunks, not coarser;
* wall clock counts from the top of this script, before torch and Warp are imported (EBRL's counts from
  launch), so start-up, kernel loading and graph capture are charged to both sides.

Stop rule: the success rate of the last 20 finished episodes reaches ``--target-success`` (``none``: off); or
``--max-seconds`` pass; or ``--total-timesteps`` env steps are spent. ``--json PATH`` writes the summary (when
and after how many env steps the target was first reached, env steps/s), the hyper-parameters and the curve
(wall-clock, env steps, success rate, mean return of the last 20 episodes, after every update).
"""

from __future__ import annotations

import time

T0 = time.monotonic()  # before the heavy imports: everything after this is charged to the peer
T0_EPOCH = time.time()  # the same instant on the wall clock (benchmarks/start_end.py)

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
from torch.distributions import Normal  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

WINDOW = 20  # episodes in the success rate and mean return, as EBRL's sim/success_rate
SEED_STRIDE = 100_003  # world i is seeded seed * SEED_STRIDE + i, as EBRL seeds env i (ebrl/sched/fleet.py)


@dataclass
class Args:
    env: str = "PandaPickCube-v0"
    num_envs: int = 2048  # configs/mjwarp_pickcube.toml: 2 groups x 1024 worlds
    seed: int = 0
    device: str = "auto"  # the batch's env.kwargs.device: auto, cpu, cuda, cuda:N
    target_success: float | None = 0.9
    stop_at_target: bool = True
    max_seconds: float = 900.0
    json: str | None = None
    torch_threads: int = 0  # 0: torch's default
    hidden: str = "256,256,256"
    init_log_std: float = -0.5
    normalize_obs: bool = True
    # EBRL's config: 600 updates of 16384 decisions x 4 steps; 32 steps of each of 2048 worlds per update
    total_timesteps: int = 600 * 2048 * 32
    num_steps: int = 32
    learning_rate: float = 3e-4
    gamma: float = 0.97
    gae_lambda: float = 0.95
    num_minibatches: int = 8
    update_epochs: int = 4
    clip_coef: float = 0.2
    ent_coef: float = 0.0
    vf_coef: float = 0.5
    max_grad_norm: float = 0.5
    target_kl: float | None = None  # EBRL has none; ManiSkill's baseline uses 0.1

    @property
    def batch_size(self) -> int:
        return self.num_envs * self.num_steps

    @property
    def minibatch_size(self) -> int:
        return max(1, self.batch_size // self.num_minibatches)

    @property
    def num_iterations(self) -> int:
        return max(1, self.total_timesteps // self.batch_size)


def parse_args(argv: list[str] | None = None) -> Args:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    for name, default in asdict(Args()).items():
        flags = ["--" + name.replace("_", "-")]
        if name == "total_timesteps":
            flags.append("--total-steps")
        if name in ("target_success", "target_kl"):
            p.add_argument(*flags, type=lambda t: None if t.lower() == "none" else float(t), default=default,
                           help="'none': off")
        elif name == "json":
            p.add_argument(*flags, default=None, help="write the summary, hyper-parameters and curve here")
        elif isinstance(default, bool):
            p.add_argument(*flags, action=argparse.BooleanOptionalAction, default=default)
        else:
            p.add_argument(*flags, type=type(default), default=default, help="default: %(default)s")
    return Args(**vars(p.parse_args(argv)))


def layer(n_in: int, n_out: int, gain: float) -> nn.Linear:
    out = nn.Linear(n_in, n_out)
    nn.init.orthogonal_(out.weight, gain)
    nn.init.zeros_(out.bias)
    return out


def mlp(n_in: int, hidden: list[int], n_out: int, out_gain: float) -> nn.Sequential:
    layers: list[nn.Module] = []
    for width in hidden:
        layers += [layer(n_in, width, float(np.sqrt(2))), nn.Tanh()]
        n_in = width
    layers.append(layer(n_in, n_out, out_gain))
    return nn.Sequential(*layers)


class Agent(nn.Module):
    """CleanRL's and ManiSkill's actor-critic: two tanh MLPs, a state-independent learned log-std."""

    def __init__(self, obs_dim: int, act_dim: int, hidden: list[int], init_log_std: float):
        super().__init__()
        self.critic = mlp(obs_dim, hidden, 1, 1.0)
        self.actor_mean = mlp(obs_dim, hidden, act_dim, 0.01)
        self.actor_logstd = nn.Parameter(torch.full((1, act_dim), float(init_log_std)))

    def get_value(self, x: torch.Tensor) -> torch.Tensor:
        return self.critic(x).view(-1)

    def get_action_and_value(self, x: torch.Tensor, action: torch.Tensor | None = None):
        mean = self.actor_mean(x)
        probs = Normal(mean, self.actor_logstd.expand_as(mean).exp())
        if action is None:
            action = probs.sample()
        return action, probs.log_prob(action).sum(1), probs.entropy().sum(1), self.critic(x).view(-1)


class RunningNorm:
    """Running mean and variance of the observations on the device (as EBRL's ``ObsNormalizer``: Chan et al.'s
    parallel update in float64, standardise and clip to +-10; mean 0 and variance 1 until the first update)."""

    def __init__(self, dim: int, device: torch.device, enabled: bool, clip: float = 10.0, eps: float = 1e-8):
        self.enabled, self.clip, self.eps = enabled, clip, eps
        self.mean = torch.zeros(dim, dtype=torch.float64, device=device)
        self.var = torch.ones(dim, dtype=torch.float64, device=device)
        self.count = 0.0
        self._refresh()

    def _refresh(self) -> None:
        self.mean32 = self.mean.float()
        self.std32 = torch.sqrt(self.var + self.eps).float()

    def __call__(self, obs: torch.Tensor) -> torch.Tensor:
        if not self.enabled:
            return obs
        return ((obs - self.mean32) / self.std32).clamp(-self.clip, self.clip)

    @torch.no_grad()
    def update(self, obs: torch.Tensor) -> None:
        if not self.enabled or len(obs) == 0:
            return
        x = obs.double()
        n = float(len(x))
        mean, var = x.mean(0), x.var(0, unbiased=False)
        total = self.count + n
        old_var = self.var if self.count else torch.zeros_like(self.var)
        delta = mean - self.mean
        m2 = old_var * self.count + var * n + delta.square() * self.count * n / total
        self.mean = self.mean + delta * n / total
        self.var = m2 / total
        self.count = total
        self._refresh()


def make_batch(args: Args) -> Any:
    """EBRL's MuJoCo Warp batch of ``num_envs`` worlds (the same physics, reward and observation code EBRL runs)."""
    from ebrl.envs.batch import MjWarpBatch
    from ebrl.envs.spec import EnvSpec

    spec = EnvSpec(id=args.env, backend="mjwarp", kwargs={"device": args.device})
    return MjWarpBatch(spec, [args.seed * SEED_STRIDE + i for i in range(args.num_envs)])


def ppo_update(agent: Agent, optimizer: torch.optim.Optimizer, args: Args, b_obs: torch.Tensor,
               b_actions: torch.Tensor, b_logprobs: torch.Tensor, b_advantages: torch.Tensor, b_returns: torch.Tensor,
               orders: list[torch.Tensor] | None = None) -> list[torch.Tensor]:
    """CleanRL's update: ``update_epochs`` passes over the batch in ``num_minibatches`` minibatches (``orders``: each
    epoch's permutation; default random), clipped surrogate, advantages normalised per minibatch, value loss,
    gradient norm clipped. Returns each step's approximate KL (on the device)."""
    kls: list[torch.Tensor] = []
    n = len(b_obs)
    for epoch in range(args.update_epochs):
        order = orders[epoch] if orders is not None else torch.randperm(n, device=b_obs.device)
        for mb in torch.tensor_split(order, args.num_minibatches):
            _, newlogprob, entropy, newvalue = agent.get_action_and_value(b_obs[mb], b_actions[mb])
            logratio = newlogprob - b_logprobs[mb]
            ratio = logratio.exp()
            with torch.no_grad():
                approx_kl = ((ratio - 1) - logratio).mean()
                kls.append(approx_kl)
            adv = b_advantages[mb]
            if len(mb) > 1:
                adv = (adv - adv.mean()) / (adv.std() + 1e-8)
            pg_loss = torch.max(-adv * ratio, -adv * torch.clamp(ratio, 1 - args.clip_coef, 1 + args.clip_coef)).mean()
            v_loss = 0.5 * ((newvalue - b_returns[mb]) ** 2).mean()
            loss = pg_loss - args.ent_coef * entropy.mean() + v_loss * args.vf_coef
            optimizer.zero_grad()
            loss.backward()
            nn.utils.clip_grad_norm_(agent.parameters(), args.max_grad_norm)
            optimizer.step()
        if args.target_kl is not None and float(approx_kl) > args.target_kl:
            break
    return kls


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    command = " ".join(shlex.quote(a) for a in [sys.executable, *(sys.argv if argv is None else argv)])
    random.seed(args.seed)
    np.random.seed(args.seed)
    torch.manual_seed(args.seed)
    if args.torch_threads > 0:
        torch.set_num_threads(args.torch_threads)
    hidden = [int(w) for w in args.hidden.split(",")]

    batch = make_batch(args)
    device = batch.device
    n, obs_dim, act_dim = batch.num_envs, batch.task.obs_size, batch.task.action_size
    episode_index = np.zeros(n, np.int64)  # each world's episode counter: episode k is seeded seed_i + 7919 k
    next_obs = batch.reset(np.arange(n), episode_index).float()

    agent = Agent(obs_dim, act_dim, hidden, args.init_log_std).to(device)
    optimizer = torch.optim.Adam(agent.parameters(), lr=args.learning_rate, eps=1e-5)
    norm = RunningNorm(obs_dim, device, args.normalize_obs)
    active = torch.ones(n, dtype=torch.bool, device=device)

    obs = torch.zeros((args.num_steps, n, obs_dim), device=device)  # raw: standardised with the update's stats
    actions = torch.zeros((args.num_steps, n, act_dim), device=device)
    logprobs, rewards, dones, values, final_values = (torch.zeros((args.num_steps, n), device=device)
                                                      for _ in range(5))
    ep_return = torch.zeros(n, device=device)
    ep_success = torch.zeros(n, dtype=torch.bool, device=device)
    returns_window: collections.deque[float] = collections.deque(maxlen=WINDOW)
    success_window: collections.deque[bool] = collections.deque(maxlen=WINDOW)
    curve: list[dict[str, Any]] = []
    episodes = successes = global_step = updates = 0
    rollout_s = update_s = 0.0
    reached: dict[str, Any] | None = None
    stop_reason = "total_timesteps"
    next_done = torch.zeros(n, device=device)
    t_envs_ready = time.monotonic() - T0
    print(f"[{t_envs_ready:7.1f} s] {n} worlds of {args.env} ready on {device}; batch {args.batch_size}, "
          f"minibatch {args.minibatch_size}, {args.num_iterations} updates at most", flush=True)

    def rate() -> float | None:
        return float(np.mean(success_window)) if success_window else None

    def mean_return() -> float | None:
        return float(np.mean(returns_window)) if returns_window else None

    def out_of_time() -> bool:
        return time.monotonic() - T0 >= args.max_seconds

    done_training = False
    for _iteration in range(1, args.num_iterations + 1):
        # ---- rollout: num_steps batched steps, partial resets of the worlds whose episode ended ----
        t_phase = time.monotonic()
        final_values.zero_()
        for step in range(args.num_steps):
            global_step += n
            obs[step] = next_obs
            dones[step] = next_done
            with torch.no_grad():
                action, logprob, _, value = agent.get_action_and_value(norm(next_obs))
            values[step] = value
            actions[step] = action
            logprobs[step] = logprob
            out = batch.step(action, active)  # the batch clips to [-1, 1], as EBRL's side
            next_obs = out.obs.float()
            rewards[step] = out.reward
            ep_return += out.reward
            if out.success is not None:
                ep_success |= out.success
            done = out.terminated | out.truncated
            next_done = done.float()
            if bool(done.any()):
                idx_t = torch.nonzero(done).view(-1)
                cut = torch.nonzero(out.truncated & ~out.terminated).view(-1)
                if len(cut):  # a time limit, not an outcome: bootstrap from the final observation's value
                    with torch.no_grad():
                        final_values[step, cut] = agent.get_value(norm(next_obs[cut]))
                ended_returns = ep_return[idx_t].tolist()
                ended_success = ep_success[idx_t].tolist()
                returns_window.extend(ended_returns)
                success_window.extend(ended_success)
                episodes += len(ended_returns)
                successes += sum(ended_success)
                ep_return[idx_t] = 0.0
                ep_success[idx_t] = False
                idx = idx_t.cpu().numpy()
                episode_index[idx] += 1
                next_obs = batch.reset(idx, episode_index[idx]).float()
                success = rate()
                if reached is None and args.target_success is not None and len(success_window) == WINDOW \
                        and success is not None and success >= args.target_success:
                    reached = {"wall_s": time.monotonic() - T0, "env_steps": global_step, "updates": updates,
                               "episodes": episodes, "success_rate": success, "return": mean_return()}
                    curve.append({**{k: v for k, v in reached.items()}, "wall_s": round(reached["wall_s"], 3),
                                  "target_reached": True})
                    if args.stop_at_target:
                        stop_reason, done_training = "target_success", True
                        break
            if out_of_time():
                break
        rollout_s += time.monotonic() - t_phase
        if done_training:
            break
        if out_of_time():
            stop_reason = "max_seconds"
            break

        # ---- GAE: dones[t] marks the first step of a new episode; truncations bootstrap (ManiSkill's ppo.py) ----
        t_phase = time.monotonic()
        with torch.no_grad():
            next_value = agent.get_value(norm(next_obs))
            advantages = torch.zeros_like(rewards)
            lastgaelam = torch.zeros(n, device=device)
            for t in reversed(range(args.num_steps)):
                not_done = 1.0 - (next_done if t == args.num_steps - 1 else dones[t + 1])
                next_values = next_value if t == args.num_steps - 1 else values[t + 1]
                delta = rewards[t] + args.gamma * (not_done * next_values + final_values[t]) - values[t]
                advantages[t] = lastgaelam = delta + args.gamma * args.gae_lambda * not_done * lastgaelam
            returns = advantages + values
        b_raw, b_actions = obs.reshape(-1, obs_dim), actions.reshape(-1, act_dim)
        b_logprobs, b_advantages, b_returns = logprobs.reshape(-1), advantages.reshape(-1), returns.reshape(-1)
        norm.update(b_raw)  # as EBRL: the batch's observations join the statistics before its gradient steps
        b_obs = norm(b_raw)

        # ---- update: epochs x minibatches of clipped-surrogate PPO ----
        kls = ppo_update(agent, optimizer, args, b_obs, b_actions, b_logprobs, b_advantages, b_returns)
        updates += 1
        update_s += time.monotonic() - t_phase
        now = time.monotonic() - T0
        success, ret = rate(), mean_return()
        kl = float(torch.stack(kls).mean())
        curve.append({"wall_s": round(now, 3), "env_steps": global_step, "updates": updates, "episodes": episodes,
                      "success_rate": success, "return": ret})
        print(f"[{now:7.1f} s] update {updates:4d}  env steps {global_step:9d}  {global_step / now:8.0f} steps/s  "
              f"episodes {episodes:7d}  success (last {WINDOW}) {'-' if success is None else f'{success:.0%}'}  "
              f"return {'-' if ret is None else f'{ret:.2f}'}  kl {kl:.4f}", flush=True)
        if out_of_time():
            stop_reason = "max_seconds"
            break

    wall_s = time.monotonic() - T0
    batch.close()
    summary = {
        "stop_reason": stop_reason, "wall_s": round(wall_s, 2), "env_start_s": round(t_envs_ready, 2),
        "started_at_epoch": T0_EPOCH,
        "env_steps": global_step, "env_steps_per_s": round(global_step / wall_s, 1),
        "rollout_env_steps_per_s": round(global_step / rollout_s, 1) if rollout_s else None,
        "updates": updates, "episodes": episodes, "successes": successes,
        "rollout_s": round(rollout_s, 2), "update_s": round(update_s, 2),
        "final_success_rate": rate(), "final_return": mean_return(), "target_success": args.target_success,
        "target_reached": None if reached is None else {k: round(v, 3) if isinstance(v, float) else v
                                                        for k, v in reached.items()},
    }
    print(f"\n{global_step} env steps in {wall_s:.1f} s: {global_step / wall_s:.0f} env steps/s overall, "
          f"{summary['rollout_env_steps_per_s']} in rollouts; {episodes} episodes, {updates} updates")
    if reached is not None:
        print(f"reached success {reached['success_rate']:.0%} after {reached['wall_s']:.1f} s wall clock "
              f"({reached['env_steps']} env steps, {reached['updates']} updates)")
    else:
        print(f"target success {args.target_success} not reached (stopped on {stop_reason})")
    if args.json:
        versions = {"python": platform.python_version(), "torch": torch.__version__}
        for module in ("warp", "mujoco_warp", "mujoco"):
            try:
                versions[module] = getattr(__import__(module), "__version__", "?")
            except ImportError:
                pass
        out_json = {
            "peer": "one-process PPO on EBRL's MuJoCo Warp batch, every tensor on its device "
                    "(as ManiSkill's and MuJoCo Playground's PPO loops)",
            "command": command, "device": str(device),
            "gpu": torch.cuda.get_device_name(device) if device.type == "cuda" else None,
            "machine": f"{platform.machine()}, {len(os.sched_getaffinity(0))} usable cores",
            "date": time.strftime("%Y-%m-%d"),
            "versions": versions,
            "summary": summary,
            "hyperparameters": {**asdict(args), "batch_size": args.batch_size, "minibatch_size": args.minibatch_size,
                                "num_iterations": args.num_iterations, "action_chunk": 1,
                                "seeds": f"seed * {SEED_STRIDE} + world index"},
            "curve": curve,
        }
        path = Path(args.json)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(out_json, indent=2) + "\n")
        print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
