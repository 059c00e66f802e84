"""PPO with GAE over chunk decisions (Schulman et al. 2017; CleanRL's ppo_continuous_action),
with the decoupled objective for stale data (Hilton et al. 2022, "Batch size-invariance for policy
optimization", eq. 2; as used by asynchronous RL systems such as AReaL).

One decision is one action chunk of K env steps: its reward is the sum of the
rewards of the steps it ran, and it is discounted by gamma**k for the k steps
it took. Segments that ended by time limit or by segment length bootstrap from
the value of ``last_obs``; terminated ones do not.

Decoupled loss: with pi_behave the policy that acted, pi_prox the policy at the
start of this update (log-probs recomputed once, before the batch joins the
observation statistics) and r = pi_theta / pi_prox,

    L = -E[ w * min(r * A, clip(r, 1 - eps, 1 + eps) * A) ],   w = min(pi_prox / pi_behave, cap)

On-policy data has pi_prox = pi_behave, w = 1: plain PPO.

``algo.prox_logp = "interpolate"`` skips the forward pass that recomputes log pi_prox: with v the
version at the start of the update (pi_prox's), b the behaviour version of a decision and the current
policy counted as version v + 1, it takes log pi_prox on the line between behaviour and current,

    log pi_prox ~ log pi_behave + alpha * (log pi_theta - log pi_behave),   alpha = (v - b) / (v - b + 1)

(log pi_theta detached, per minibatch step): alpha = 0 on-policy, so again plain PPO.
"""

from __future__ import annotations

import collections
import dataclasses
import math
from dataclasses import dataclass
from typing import Any, Callable, Sequence

import numpy as np
import torch
from torch import nn

from ebrl.algos.parallel import Methods
from ebrl.messages import TrajectorySegment, from_wire, to_wire
from ebrl.algos.staleness import fresh_suffix, split


def gae(rewards: np.ndarray, values: np.ndarray, discounts: np.ndarray, last_value: float,
        lam: float) -> tuple[np.ndarray, np.ndarray]:
    """Generalised advantage estimation over one segment.

    delta_t = r_t + gamma_t * V(s_{t+1}) - V(s_t);  A_t = delta_t + gamma_t * lambda * A_{t+1}
    where gamma_t = gamma**k_t, V(s_T) = ``last_value`` (0 for a terminal state).
    Returns advantages and returns (A_t + V(s_t)).
    In float64 throughout (a float32 sum of large rewards overflows where float64 does not); the caller checks
    the result is finite before it is cast down.
    """
    return gae_segments(rewards, values, discounts, np.array([len(rewards)]), np.array([last_value]), lam)


def gae_segments(rewards: np.ndarray, values: np.ndarray, discounts: np.ndarray, lengths: np.ndarray,
                 last_values: np.ndarray, lam: float) -> tuple[np.ndarray, np.ndarray]:
    """:func:`gae` of many segments at once: the per-decision arrays hold the segments one after another
    (``lengths[s]`` >= 1 decisions each), ``last_values[s]`` is segment ``s``'s V(s_T). The recursion runs
    backwards from every segment's end together, one vector step per decision of the longest segment, with
    the same float64 operations in the same order as one segment at a time: the results are identical. A batch
    from vectorized groups holds thousands of short segments, and a Python loop per decision of each was most of
    the host time training spent building it."""
    rewards, values = np.asarray(rewards, np.float64), np.asarray(values, np.float64)
    discounts, lengths = np.asarray(discounts, np.float64), np.asarray(lengths, np.int64)
    order = np.argsort(-lengths, kind="stable")  # longest first: the segments still running are a prefix
    ends = (np.cumsum(lengths) - 1)[order]  # each segment's last decision
    running = len(lengths) - np.cumsum(np.bincount(lengths, minlength=int(lengths.max(initial=0)) + 1))
    next_value = np.asarray(last_values, np.float64)[order]
    lastgaelam = np.zeros(len(lengths), dtype=np.float64)
    advantages = np.zeros(len(rewards), dtype=np.float64)
    for back in range(int(lengths.max(initial=0))):  # the decision ``back`` before each segment's last
        k = running[back]  # segments longer than ``back``
        t = ends[:k] - back
        delta = rewards[t] + discounts[t] * next_value[:k] - values[t]
        lastgaelam[:k] = delta + discounts[t] * lam * lastgaelam[:k]
        advantages[t] = lastgaelam[:k]
        next_value[:k] = values[t]
    return advantages, advantages + values


FLOAT32_SAFE = 1e30  # returns beyond this would overflow float32 once squared in the value loss


class BadBatch(ValueError):
    """Every decision of a batch was left out (its advantages or returns were not finite); ``dropped`` says how
    many decisions."""

    def __init__(self, dropped: int):
        super().__init__(f"no decision of the batch had finite advantages and returns ({dropped} dropped)")
        self.dropped = dropped


@dataclass
class Batch:
    obs: torch.Tensor
    actions: torch.Tensor
    latents: torch.Tensor
    logprobs: torch.Tensor
    advantages: torch.Tensor
    returns: torch.Tensor | None  # value targets; None: no critic to train (GRPO)
    values: torch.Tensor
    versions: np.ndarray
    normalize_advantages: bool = True  # per minibatch (PPO); GRPO's are normalised per group already
    diagnostics: dict[str, float] = dataclasses.field(default_factory=dict)  # reported with the update's stats
    dropped: int = 0  # decisions left out as they were built (advantages or returns not finite)

    def __len__(self) -> int:
        return self.obs.shape[0]

    def to(self, device: torch.device) -> "Batch":
        """The same batch with its tensors on ``device`` (pinned, non-blocking copies to a GPU)."""
        if self.obs.device == device:
            return self
        cuda = device.type == "cuda"

        def move(t: torch.Tensor | None) -> torch.Tensor | None:
            if t is None:
                return None
            return (t.pin_memory() if cuda and t.device.type == "cpu" else t).to(device, non_blocking=cuda)

        return dataclasses.replace(self, **{f.name: move(getattr(self, f.name)) for f in dataclasses.fields(self)
                                            if isinstance(getattr(self, f.name), torch.Tensor)})


def _device(model: nn.Module) -> torch.device:
    return next(model.parameters()).device


def build_batch(segments: Sequence[TrajectorySegment], model: nn.Module, gamma: float, lam: float,
                values: str = "current") -> Batch:
    """Advantages for every segment, concatenated.

    Every value in a segment's GAE comes from one critic. ``values = "current"`` (the default): the critic the
    update starts from (``model``), for every V(s_t) and the bootstrap V(s_T) alike, one forward pass over the
    batch -- as AReaL computes values on the trainer, at training time. ``"behaviour"``: the values the acting
    version's critic gave when the data was collected (``segment.values``), with the bootstrap still from
    ``model``; on stale data each segment's last delta then mixes two critics (EBRL's earlier behaviour,
    kept to measure the difference). On-policy both are the same critic.

    ``batch.diagnostics["value_drift"]`` is the root mean square of (current - behaviour) values: how far
    the critic moved since the data was acted (0 on-policy).
    """
    device = _device(model)
    lengths = np.array([len(s.obs) for s in segments], dtype=np.int64)
    needs_bootstrap = [i for i, s in enumerate(segments) if s.end != "terminated"]
    last_values = np.zeros(len(segments), dtype=np.float32)
    obs = np.concatenate([s.obs for s in segments])
    behave_values = np.concatenate([s.values for s in segments])
    with torch.no_grad():
        if needs_bootstrap:
            last_obs = torch.as_tensor(np.stack([segments[i].last_obs for i in needs_bootstrap])).to(device)
            last_values[needs_bootstrap] = model.value(last_obs).float().cpu().numpy()
        if values == "current":
            current = model.value(torch.as_tensor(obs).to(device)).float().cpu().numpy().astype(np.float32)
        elif values == "behaviour":
            current = behave_values
        else:
            raise ValueError(f"values = {values!r}: 'current' or 'behaviour'")
    steps = np.concatenate([s.steps for s in segments])
    rewards = np.concatenate([s.rewards for s in segments])
    advs, rets = gae_segments(rewards, current, gamma ** steps.astype(np.float64), lengths, last_values, lam)
    bad = ~(np.isfinite(advs) & np.isfinite(rets) & (np.abs(rets) < FLOAT32_SAFE))
    bad_segment = np.logical_or.reduceat(bad, np.cumsum(lengths) - lengths) if len(bad) else bad
    dropped = int(lengths[bad_segment].sum())  # nothing to learn from: left out of the batch, counted by the caller
    if dropped == len(bad):
        raise BadBatch(dropped)
    keep = np.repeat(~bad_segment, lengths) if dropped else slice(None)

    def cat(name: str) -> torch.Tensor:
        return torch.as_tensor(np.concatenate([getattr(s, name) for s in segments])[keep])

    used_values = current[keep]
    drift = float(np.sqrt(np.mean((used_values - behave_values[keep]) ** 2)))
    return Batch(obs=torch.as_tensor(obs[keep]), actions=cat("actions"), latents=cat("latents"),
                 logprobs=cat("logprobs"), advantages=torch.as_tensor(advs[keep].astype(np.float32)),
                 returns=torch.as_tensor(rets[keep].astype(np.float32)), values=torch.as_tensor(used_values),
                 versions=np.concatenate([s.versions for s in segments])[keep],
                 diagnostics={"value_drift": drift}, dropped=dropped)


def policy_loss(logp: torch.Tensor, prox_logp: torch.Tensor, behave_logp: torch.Tensor, adv: torch.Tensor,
                clip: float, cap: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The decoupled clipped surrogate over decisions (module docstring), as (loss, w, r):

        r = pi_theta / pi_prox,   w = min(pi_prox / pi_behave, cap)  (no gradient through w)
        L = mean( w * max(-A * r, -A * clip(r, 1 - clip, 1 + clip)) )

    With pi_prox = pi_behave (on-policy, or ``algo.decoupled = false``) w = 1: CleanRL's PPO loss."""
    weight = (prox_logp - behave_logp).detach().exp().clamp(max=cap)
    ratio = (logp - prox_logp).exp()
    loss = (weight * torch.max(-adv * ratio, -adv * ratio.clamp(1 - clip, 1 + clip))).mean()
    return loss, weight, ratio


def make_adam(params: Any, lr: float, eps: float = 1e-5) -> torch.optim.Optimizer:
    """Adam, fused where torch has a fused kernel for these parameters (one kernel per step instead of several
    per tensor; on CUDA, and on the CPU since torch 2.4): a fused Adam also takes ``found_inf`` and skips a
    step on the device, with no read back to the host (:meth:`PPO.update`)."""
    params = list(params)
    try:
        return torch.optim.Adam(params, lr=lr, eps=eps, fused=True)
    except (RuntimeError, TypeError):  # a device or dtype the fused kernel does not take
        return torch.optim.Adam(params, lr=lr, eps=eps)


def skips_on_device(optimizer: torch.optim.Optimizer) -> bool:
    """Whether ``optimizer.step`` honours ``optimizer.found_inf`` (torch's fused Adam: AMP's grad scaler sets
    it), so that a bad step is skipped without the host reading whether it was bad. A checkpoint made by an
    unfused optimizer restores ``fused = None``: such an optimizer checks on the host, each step."""
    return isinstance(optimizer, torch.optim.Adam) and all(g.get("fused") for g in optimizer.param_groups)


STEP_STATS = ("policy_loss", "value_loss", "entropy", "approx_kl", "clipfrac")  # means over the steps taken


class PPO:
    """Clipped-surrogate PPO updates of a policy with ``evaluate(obs, actions)``."""

    def __init__(self, model: nn.Module, algo_cfg: Any, lr: float, seed: int = 0, net: nn.Module | None = None):
        """``net`` calls the model's methods through ``forward`` (``ebrl.algos.parallel.Methods``, wrapped in
        DistributedDataParallel when several ranks train); the gradient steps go through it."""
        self.model, self.cfg = model, algo_cfg
        self.net = net if net is not None else Methods(model)
        self.lr = lr
        self._optimizer: torch.optim.Optimizer | None = None
        self.generator = torch.Generator().manual_seed(seed)

    @property
    def optimizer(self) -> torch.optim.Optimizer:
        """Adam over the model's trainable parameters (:func:`make_adam`; a VLA's frozen base weights are not
        its), made on first use: torch's first optimizer imports torch._dynamo, most of a second of CPU, which a
        new run spends after its first weights are out (``prepare``) rather than before generation can act."""
        if self._optimizer is None:
            self._optimizer = make_adam([p for p in self.model.parameters() if p.requires_grad], self.lr)
        return self._optimizer

    @optimizer.setter
    def optimizer(self, optimizer: torch.optim.Optimizer) -> None:
        self._optimizer = optimizer

    def prepare(self) -> None:
        """Make the optimizer now (train: once v0 is published, while the first batch is collected)."""
        _ = self.optimizer

    def proximal(self, batch: Batch) -> torch.Tensor | None:
        """log pi_prox of ``batch`` where the objective recomputes it (``algo.decoupled``, ``prox_logp =
        "recompute"``), else None. The learner calls it before the observation normaliser takes in the batch:
        pi_prox is the policy that starts the update, the one a decision was drawn from when the data is
        on-policy, so there w = 1 and the update is plain PPO's. Computed after the merge, w would instead
        measure how far the normaliser moved and weight each decision by that noise."""
        if not getattr(self.cfg, "decoupled", False) or getattr(self.cfg, "prox_logp", "recompute") != "recompute":
            return None
        with torch.no_grad():
            return self.net("evaluate", batch.obs, batch.actions, batch.latents)[0]

    def update(self, batch: Batch, scale: float = 1.0, version: int | None = None,
               prox: torch.Tensor | None = None) -> dict[str, float]:
        """``epochs`` x ``minibatches`` gradient steps, always exactly that many (data-parallel ranks step in
        lockstep); ``scale = 0`` takes the steps with zero gradients (a rank that got no data this time).
        ``version``: the policy version being updated (default: the newest in the batch), for interpolation.
        ``prox``: log pi_prox from :meth:`proximal` (default: recomputed here, where the objective needs it).

        A step whose loss or gradient norm is not finite is skipped (AMP's answer to a bad step) and the
        decisions that made it leave the batch: those whose own log-prob, value or loss term is not finite,
        else the whole minibatch. On a GPU the host waits for the device only once per epoch: the statistics
        add up on the device, a fused Adam skips a bad step by itself (``found_inf``), and which steps were bad
        is read at the epoch's end -- each decision is in one minibatch per epoch, so dropping its data then
        is as soon as it matters. An optimizer that cannot skip on the device is checked after each step."""
        cfg, n, device = self.cfg, len(batch), batch.obs.device
        decoupled = getattr(cfg, "decoupled", False)
        interpolate = decoupled and getattr(cfg, "prox_logp", "recompute") == "interpolate"
        cap = getattr(cfg, "behave_weight_cap", math.inf)
        means: dict[str, list[torch.Tensor]] = {}  # per-step values on the device, averaged and read at the end
        alpha = None
        if interpolate:
            lag = torch.as_tensor((version if version is not None else batch.versions.max()) - batch.versions,
                                  dtype=torch.float32, device=device).clamp(min=0)
            alpha = lag / (lag + 1)  # log pi_prox and the weights: per minibatch step (_step)
        elif decoupled:
            prox = prox if prox is not None else self.proximal(batch)  # log pi_prox, once per update
            self._behaviour_stats(means, prox - batch.logprobs, cap)
        else:
            prox = batch.logprobs  # pi_prox = pi_behave: weight 1, plain PPO
        if prox is not None:
            means["behave_weight_mean"] = [(prox - batch.logprobs).exp().clamp(max=cap).mean()]
        taken = torch.zeros(len(STEP_STATS) + 1, dtype=torch.float64, device=device)  # sums of STEP_STATS, steps
        keep = torch.ones(n, dtype=torch.bool)  # decisions still in the batch (a bad step drops its data)
        skipped = dropped = 0
        for _ in range(cfg.epochs):
            order = torch.randperm(n, generator=self.generator)
            parts = [idx[keep[idx]] for idx in torch.tensor_split(order, cfg.minibatches)]
            scales = [scale if len(idx) else 0.0 for idx in parts]
            parts = [idx if len(idx) else order[:1] for idx in parts]  # nothing left: a step with zero gradients
            moved = torch.cat(parts)  # the epoch's indices to the device in one copy that the host does not wait on
            moved = (moved.pin_memory() if device.type == "cuda" else moved).to(device, non_blocking=True)
            steps: list[tuple[torch.Tensor, torch.Tensor, torch.Tensor]] = []  # (indices, step fine, own fine)
            for idx, on, step_scale in zip(parts, torch.split(moved, [len(i) for i in parts]), scales):
                fine, own, values = self._step(batch, on, len(idx), step_scale, prox, alpha, cap, means)
                steps.append((idx, fine, own))
                taken += torch.where(fine, values, 0.0)  # a skipped step's numbers are not averaged
            for idx, own in self._bad(steps):  # this epoch's verdicts: one read of the device
                bad = idx[~own] if not bool(own.all()) else idx
                keep[bad] = False
                skipped, dropped = skipped + 1, dropped + len(bad)
        return {**self._read(taken, means), **self.batch_stats(batch), "steps_skipped": float(skipped),
                "decisions_dropped": float(dropped)}

    def _step(self, batch: Batch, on: torch.Tensor, size: int, step_scale: float, prox: torch.Tensor | None,
              alpha: torch.Tensor | None, cap: float, means: dict[str, list[torch.Tensor]]
              ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """One gradient step on the decisions ``on`` (indices on the device, ``size`` of them): (step finite,
        each decision's own terms finite, the step's ``STEP_STATS`` and a 1), all on the device. ``prox``: log
        pi_prox of the batch; None: interpolated with ``alpha`` from this step's log-probs."""
        cfg = self.cfg
        newlogprob, entropy, newvalue = self.net("evaluate", batch.obs[on], batch.actions[on], batch.latents[on])
        behave = batch.logprobs[on]
        if prox is None:
            prox_mb = behave + alpha[on] * (newlogprob.detach() - behave)
            self._behaviour_stats(means, prox_mb - behave, cap)
        else:
            prox_mb = prox[on]
        adv = batch.advantages[on]
        if batch.normalize_advantages and size > 1:
            adv = (adv - adv.mean()) / (adv.std() + 1e-8)
        pg_loss, weight_mb, ratio = policy_loss(newlogprob, prox_mb, behave, adv, cfg.clip, cap)
        if prox is None:
            means.setdefault("behave_weight_mean", []).append(weight_mb.mean())
        if batch.returns is None:
            v_loss = torch.zeros((), device=on.device)
        else:
            v_loss = 0.5 * ((newvalue - batch.returns[on]) ** 2).mean()
        ent = entropy.mean()
        loss = step_scale * (pg_loss - cfg.ent_coef * ent + cfg.vf_coef * v_loss)
        self.optimizer.zero_grad()
        loss.backward()
        norm = nn.utils.clip_grad_norm_(self.model.parameters(), cfg.max_grad_norm)
        norm = norm.full_tensor() if hasattr(norm, "full_tensor") else norm  # sharded (fsdp): a DTensor
        fine = torch.isfinite(loss) & torch.isfinite(norm)
        own = torch.isfinite(newlogprob) & torch.isfinite(newvalue) & torch.isfinite(ratio * adv)
        if batch.returns is not None:
            own &= torch.isfinite((newvalue - batch.returns[on]) ** 2)
        if skips_on_device(self.optimizer):
            self.optimizer.found_inf = (~fine).float()  # fused Adam: a bad step leaves weights and state
            try:
                self.optimizer.step()
            finally:
                del self.optimizer.found_inf
        elif bool(fine):
            self.optimizer.step()
        with torch.no_grad():
            values = torch.stack([t.double() for t in (
                pg_loss, v_loss, ent, ((ratio - 1) - (newlogprob - prox_mb)).mean(),
                ((ratio - 1.0).abs() > cfg.clip).float().mean(), torch.ones((), device=on.device))])
        return fine, own.detach(), values

    @staticmethod
    def _bad(steps: list[tuple[torch.Tensor, torch.Tensor, torch.Tensor]]) -> list[tuple[torch.Tensor, torch.Tensor]]:
        """(indices, ``own`` mask on the host) of the steps that were not finite (one read of the device, and
        one more for each bad step: rare)."""
        if not steps:
            return []
        fine = torch.stack([f for _, f, _ in steps]).cpu()
        return [(idx, own.cpu()) for (idx, _, own), ok in zip(steps, fine.tolist()) if not ok]

    @staticmethod
    def _read(taken: torch.Tensor, means: dict[str, list[torch.Tensor]]) -> dict[str, float]:
        """The update's statistics, read from the device at once: each of ``STEP_STATS`` averaged over the steps
        taken (absent where none was), each of ``means`` over its values."""
        names = list(means)
        tensors = [taken] + [torch.stack([t.double() for t in means[k]]).mean().reshape(1) for k in names]
        values = torch.cat(tensors).tolist()
        count, out = values[len(STEP_STATS)], {}
        if count:
            out = {name: values[i] / count for i, name in enumerate(STEP_STATS)}
        out.update(zip(names, values[len(STEP_STATS) + 1:]))
        return out

    @staticmethod
    def _behaviour_stats(means: dict[str, list[torch.Tensor]], log_w: torch.Tensor, cap: float) -> None:
        """How far the behaviour policy is from pi_prox, over decisions: KL(pi_behave || pi_prox) by the k3
        estimator (mean of w - 1 - log w, w = pi_prox / pi_behave, >= 0, 0 on-policy), the share of weights
        above the cap, the largest weight (device tensors, read with the update's other numbers)."""
        log_w = log_w.detach().float()
        w = log_w.exp()
        means.setdefault("behave_kl", []).append((w - 1 - log_w).mean())
        means.setdefault("behave_weight_capped", []).append((w > cap).float().mean())
        means.setdefault("behave_weight_max", []).append(w.max())

    @staticmethod
    def batch_stats(batch: Batch) -> dict[str, float]:
        """What the update learned from: raw advantages (before per-minibatch normalisation), how well the
        values used in GAE explain the returns (1 - Var(returns - values) / Var(returns)), and the batch's
        diagnostics (``value_drift``)."""
        out = dict(batch.diagnostics)
        if len(batch) < 2:
            return out
        adv = batch.advantages.double()  # float64: the squares of large returns overflow float32
        out.update(adv_mean=adv.mean().item(), adv_std=adv.std().item())
        if batch.returns is not None:
            ret = batch.returns.double()
            var = ret.var().item()
            if var > 0:
                out["explained_variance"] = 1.0 - (ret - batch.values.double()).var().item() / var
        return out


class SegmentCollector:
    """PPO's side of the train service: segments in arrival order, at most ``max_pending`` decisions
    (beyond it the oldest segments are dropped, counted); a batch is the oldest ``batch_size`` decisions,
    decisions more than ``max_staleness`` versions behind cut off (counted).

    A batch is exactly ``batch_size`` decisions: the segment it ends in is split (``staleness.split``), its
    rest the first of the next batch. Taking it whole instead (up to a segment's length more) made every update
    wait for that many more decisions than the one before, so the updates fell behind the iterations they
    learn from, and generation held groups back at iteration boundaries (``Schedule.min_version``) while
    training caught up (segments cut at episode ends do not line up with batches). On heavy-tailed 2 ms steps
    the groups waited for actions 8.6 % of their time, two thirds of it in such waits; with exact batches, 3.7 %."""

    def __init__(self, algo_cfg: Any, max_pending: int, max_staleness: int, count: Callable[[str, float], None]):
        self.cfg, self.max_pending, self.max_staleness, self.count = algo_cfg, max_pending, max_staleness, count
        self.pending: collections.deque[TrajectorySegment] = collections.deque()
        self.pending_steps = 0

    @property
    def ready_steps(self) -> int:
        return self.pending_steps

    def add(self, seg: TrajectorySegment) -> None:
        self.pending.append(seg)
        self.pending_steps += len(seg.obs)
        while self.pending_steps - len(self.pending[0].obs) >= self.max_pending:
            dropped = self.pending.popleft()
            self.pending_steps -= len(dropped.obs)
            self.count("train/segments_dropped_overflow", 1)

    def take(self, version: int, batch_size: int) -> list[TrajectorySegment]:
        """Oldest segments first, until ``batch_size`` decisions. A stale prefix is cut off, which leaves
        the suffix's GAE exact."""
        segments, steps = [], 0
        while self.pending and steps < batch_size:
            seg = self.pending.popleft()
            self.pending_steps -= len(seg.obs)
            seg, dropped = fresh_suffix(seg, version, self.max_staleness)
            if dropped:
                self.count("train/stale_dropped", dropped)
            if seg is None:
                continue
            if steps + len(seg.obs) > batch_size:
                seg, rest = split(seg, batch_size - steps)
                self.pending.appendleft(rest)
                self.pending_steps += len(rest.obs)
            segments.append(seg)
            steps += len(seg.obs)
        return segments

    @staticmethod
    def to_wire(seg: TrajectorySegment) -> dict[str, Any]:
        """One item of ``take`` as it travels between training ranks (``ebrl.algos.parallel``)."""
        return to_wire(seg)

    @staticmethod
    def from_wire(raw: Any) -> TrajectorySegment:
        return from_wire(TrajectorySegment, raw)

    def segments(self) -> list[TrajectorySegment]:
        """Every buffered segment, oldest first (what a stopping train hands over)."""
        return list(self.pending)

    @staticmethod
    def size(seg: TrajectorySegment) -> int:
        """Decisions of one item of ``take``."""
        return len(seg.obs)

    def build(self, segments: list[TrajectorySegment], model: nn.Module) -> Batch:
        return build_batch(segments, model, self.cfg.gamma, self.cfg.gae_lambda, self.cfg.gae_values)
