"""Soft actor-critic (Haarnoja et al. 2018, "Soft Actor-Critic Algorithms and Applications"): twin Q critics with
target networks, a tanh-squashed Gaussian actor (:class:`~ebrl.policies.squashed.ChunkSquashedMLP`) and automatic
entropy tuning; as Stable-Baselines3's SAC, over chunk decisions.

One gradient step on a minibatch of transitions (:class:`~ebrl.algos.replay.ReplayBatch`):

    y      = r + gamma^k (1 - d) * ( min_j Q'_j(s', a') - alpha log pi(a' | s') ),   a' ~ pi(. | s')
    L_Q    = sum_j mean (Q_j(s, a) - y)^2 / 2                 (critics; SB3's 0.5 * sum of the two MSEs)
    L_pi   = mean( alpha log pi(a~ | s) - min_j Q_j(s, a~) ),   a~ ~ pi(. | s), reparameterised
    L_alpha = -mean( log alpha * (log pi(a~ | s) + H_target) ),  H_target = -(K x A) by default
    Q'_j <- (1 - tau) Q'_j + tau Q_j

with ``r`` the chunk's summed reward and ``k`` the env steps it ran. The critics see the actor's standardised
observations (its ``obs_norm``, without gradients into its statistics) and the chunk in the squashed [-1, 1] scale.
A step whose losses or gradient norms are not finite is skipped as a whole -- no optimizer and no target moves --
and counted (the bad-number rule of ``ebrl.algos.ppo``).
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import nn

from ebrl.algos.ppo import make_adam
from ebrl.algos.replay import ReplayBatch
from ebrl.policies.squashed import ChunkSquashedMLP


@dataclass
class SACSettings:
    """SAC's hyper-parameters (``[algo]`` of a config with ``name = "sac"``; defaults: Stable-Baselines3's)."""

    gamma: float = 0.99
    tau: float = 0.005
    lr: float = 3e-4
    init_alpha: float = 1.0  # SB3's ent_coef = "auto" starts at 1.0
    target_entropy: float | None = None  # None: -(K x A)
    critic_hidden: tuple[int, ...] = (256, 256)
    max_grad_norm: float = math.inf  # SB3 does not clip


class TwinQ(nn.Module):
    """Two independent Q networks over (standardised observation, squashed chunk), as one: each layer's two weight
    matrices stacked, so that a forward pass is one batched matrix product per layer instead of two. Each network
    is initialised as ``relu_mlp``'s (orthogonal, gain sqrt 2; the last layer gain 1, PyTorch's default scale)."""

    def __init__(self, obs_size: int, action_size: int, hidden: list[int]):
        super().__init__()
        sizes = [obs_size + action_size, *hidden, 1]
        self.weights, self.biases = nn.ParameterList(), nn.ParameterList()
        for i, (n_in, n_out) in enumerate(zip(sizes[:-1], sizes[1:])):
            w = torch.empty(2, n_in, n_out)  # x @ w: [in, out] per network
            for net in range(2):
                nn.init.orthogonal_(w[net], 1.0 if i == len(sizes) - 2 else math.sqrt(2))
            self.weights.append(nn.Parameter(w))
            self.biases.append(nn.Parameter(torch.zeros(2, 1, n_out)))

    def forward(self, obs: torch.Tensor, actions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        h = torch.cat([obs, actions], -1).unsqueeze(0).expand(2, -1, -1)
        last = len(self.weights) - 1
        for i, (w, b) in enumerate(zip(self.weights, self.biases)):
            h = torch.baddbmm(b, h, w)
            if i < last:
                h = torch.relu(h)
        return h[0, :, 0], h[1, :, 0]


class SAC:
    """The critics, their targets, the temperature and the three optimizers around ``actor``; :meth:`step` takes
    one gradient step of each."""

    def __init__(self, actor: ChunkSquashedMLP, settings: SACSettings):
        self.actor, self.cfg = actor, settings
        device, n_act = actor.device, actor.chunk * actor.action_dim
        self.critics = TwinQ(actor.obs_dim, n_act, list(settings.critic_hidden)).to(device)
        self.targets = copy.deepcopy(self.critics).requires_grad_(False)
        self.log_alpha = torch.tensor(math.log(settings.init_alpha), device=device, requires_grad=True)
        self.target_entropy = float(-n_act if settings.target_entropy is None else settings.target_entropy)
        # Adam with torch's default eps, as SB3's; fused (one kernel a step) where torch has the kernel
        self.actor_opt = make_adam(self._actor_params(), settings.lr, eps=1e-8)
        self.critic_opt = make_adam(self.critics.parameters(), settings.lr, eps=1e-8)
        self.alpha_opt = make_adam([self.log_alpha], settings.lr, eps=1e-8)
        self.skipped = 0  # gradient steps skipped (not finite)

    def _actor_params(self) -> list[nn.Parameter]:
        """The actor's trainable parameters (the observation statistics are buffers, not among them)."""
        return [p for p in self.actor.parameters() if p.requires_grad]

    @property
    def alpha(self) -> float:
        return float(self.log_alpha.detach().exp())

    def tensors(self, batch: ReplayBatch) -> dict[str, torch.Tensor]:
        """The batch on the actor's device, the observations standardised (no gradient) and the chunks squashed."""
        device = self.actor.device
        with torch.no_grad():
            obs = self.actor.flat(torch.as_tensor(batch.obs, dtype=torch.float32, device=device))
            next_obs = self.actor.flat(torch.as_tensor(batch.next_obs, dtype=torch.float32, device=device))
            actions = self.actor.from_env(torch.as_tensor(batch.actions, dtype=torch.float32, device=device))
        discount = torch.as_tensor(self.cfg.gamma ** batch.steps.astype(np.float64) * ~batch.terminal,
                                   dtype=torch.float32, device=device)
        return {"obs": obs, "next_obs": next_obs, "actions": actions,
                "rewards": torch.as_tensor(batch.rewards, dtype=torch.float32, device=device), "discount": discount}

    def step(self, batch: ReplayBatch) -> dict[str, float]:
        """One gradient step of the temperature, the critics and then the actor (against the stepped critics, as
        Stable-Baselines3 orders them), then the targets' soft update; the step's numbers. Where the temperature's
        or the critics' loss or gradient is not finite nothing moves; where only the actor's is, the actor and the
        targets stay. Either is counted in ``steps_skipped``."""
        t, alpha = self.tensors(batch), self.log_alpha.detach().exp()
        a, logp = self.actor.rsample_flat(t["obs"])
        alpha_loss = -(self.log_alpha * (logp.detach() + self.target_entropy)).mean()
        with torch.no_grad():
            next_a, next_logp = self.actor.rsample_flat(t["next_obs"])
            q1_t, q2_t = self.targets(t["next_obs"], next_a)
            target = t["rewards"] + t["discount"] * (torch.min(q1_t, q2_t) - alpha * next_logp)
        q1, q2 = self.critics(t["obs"], t["actions"])
        critic_loss = 0.5 * ((q1 - target).square().mean() + (q2 - target).square().mean())
        first = self._gradients([(alpha_loss, [self.log_alpha], self.alpha_opt),
                                 (critic_loss, list(self.critics.parameters()), self.critic_opt)])
        if first is None:
            self.skipped += 1
            return {"steps_skipped": 1.0}
        q1_pi, q2_pi = self.critics(t["obs"], a)  # the stepped critics
        actor_loss = (alpha * logp - torch.min(q1_pi, q2_pi)).mean()
        second = self._gradients([(actor_loss, self._actor_params(), self.actor_opt)])
        out = {"alpha_loss": first[0], "critic_loss": first[1], "alpha": float(alpha),
               "entropy": float(-logp.detach().mean()), "q_mean": float(torch.min(q1, q2).detach().mean()),
               "steps_skipped": 0.0}
        if second is None:
            self.skipped += 1
            return {**out, "steps_skipped": 1.0}
        self.soft_update()
        return {**out, "actor_loss": second[0]}

    def _gradients(self, parts: list[tuple[torch.Tensor, list[torch.Tensor], torch.optim.Optimizer]]
                   ) -> list[float] | None:
        """Each (loss, parameters, optimizer): the loss's gradients into its parameters (clipped to
        ``max_grad_norm``); the optimizers step only if every loss and gradient norm is finite. The losses, or
        None where something was not finite (then no optimizer stepped and the gradients are cleared)."""
        checks = []
        for loss, params, opt in parts:
            opt.zero_grad(set_to_none=True)
            loss.backward(inputs=params)
            checks += [loss.detach(), nn.utils.clip_grad_norm_(params, self.cfg.max_grad_norm)]
        values = torch.stack(checks).tolist()  # one read of the device per part
        if not all(math.isfinite(v) for v in values):
            for _, _, opt in parts:
                opt.zero_grad(set_to_none=True)
            return None
        for _, _, opt in parts:
            opt.step()
        return values[0::2]

    @torch.no_grad()
    def soft_update(self) -> None:
        """Q' <- (1 - tau) Q' + tau Q, every parameter (Polyak averaging)."""
        tau = self.cfg.tau
        for target, source in zip(self.targets.parameters(), self.critics.parameters()):
            target.lerp_(source, tau)

    def state(self) -> dict[str, Any]:
        """Everything beyond the actor a restart needs: critics, targets, temperature, optimizers (the samples'
        noise is torch's global generator, which a checkpoint keeps)."""
        return {"critics": self.critics.state_dict(), "targets": self.targets.state_dict(),
                "log_alpha": self.log_alpha.detach().clone(), "actor_opt": self.actor_opt.state_dict(),
                "critic_opt": self.critic_opt.state_dict(), "alpha_opt": self.alpha_opt.state_dict()}

    def load_state(self, state: dict[str, Any]) -> None:
        self.critics.load_state_dict(state["critics"])
        self.targets.load_state_dict(state["targets"])
        with torch.no_grad():
            self.log_alpha.copy_(state["log_alpha"])
        self.actor_opt.load_state_dict(state["actor_opt"])
        self.critic_opt.load_state_dict(state["critic_opt"])
        self.alpha_opt.load_state_dict(state["alpha_opt"])
