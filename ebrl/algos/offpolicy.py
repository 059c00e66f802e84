"""SAC behind the algorithm interface (``ebrl.algos.algorithm``): segments into the replay, gradient steps from it.

Each update takes the new decisions (``train.batch_size`` of them; with ``algo.keep_utd = false``, all that
arrived), sends them to the run's replay service (``ebrl/services/replay.py``, through
:class:`~ebrl.algos.replaylink.ReplayLink`) and runs ``algo.utd`` gradient steps per env step they hold
(:class:`~ebrl.algos.sac.SAC`, each on ``replay.batch_size`` transitions the replay drew uniformly), once
training has sent ``replay.learning_starts`` transitions; until then generation acts uniformly within the action
bounds (the actor's ``warmup`` buffer, published with its weights), as Stable-Baselines3 does. The ratio is
kept on average, not per update: the fraction left over carries to the next. ``train/utd`` reports the ratio
achieved so far, from training's own counts. The minibatches come in :class:`~ebrl.messages.ReplaySample`
messages of several each (:func:`~ebrl.algos.replay.batches_per_sample`); the next is asked for before the
gradient steps on the one in hand.

Whether simulators wait for training is the schedule's (``ebrl.sched.modes``): with ``algo.keep_utd`` (the
default) generation holds a group back when its next iteration is more than ``algo.max_staleness`` updates ahead
of training, as for PPO, so the ratio holds and simulators slow down when training cannot keep up; without it
they never wait, every update learns from all that arrived and the ratio drops. Data is never dropped for being
stale: off-policy learning is what a replay is for.
"""

from __future__ import annotations

import logging
from typing import Any, Callable

import numpy as np
import torch

from ebrl import devices
from ebrl.algos.algorithm import Algorithm, Learned, Optimizers
from ebrl.algos.ppo import SegmentCollector
from ebrl.algos.replay import FIELDS, batches_per_sample, transitions
from ebrl.algos.sac import SAC, SACSettings
from ebrl.policies.registry import trained_by_problem

log = logging.getLogger(__name__)

NEVER_STALE = 1 << 62  # an off-policy collector's staleness bound: none


class ReplayCollector(SegmentCollector):
    """New segments in arrival order, never cut for staleness; ``take_all``: an update takes all that arrived."""

    def __init__(self, algo_cfg: Any, max_pending: int, take_all: bool, count: Callable[[str, float], None]):
        super().__init__(algo_cfg, max_pending, NEVER_STALE, count)
        self.take_all = take_all

    def take(self, version: int, batch_size: int) -> list:
        return super().take(version, max(batch_size, self.pending_steps) if self.take_all else batch_size)


class SACAlgorithm(Algorithm):
    """Soft actor-critic over a replay of chunk decisions (``policy.kind = "squashed"``)."""

    name = "sac"
    uses_replay = True

    def __init__(self, model: Any, cfg: Any, info: Any, telemetry: Any, device: torch.device):
        super().__init__(model, cfg, info, telemetry, device)
        if problem := trained_by_problem(model, self.name):  # sac trains a tanh-squashed actor (rsample_flat)
            raise ValueError(problem)
        if info.layout.byte_size:
            raise ValueError("algo.name = 'sac' learns from float observations; this env's have camera images "
                             f"({', '.join(f.name for f in info.layout.fields if f.uint8)}, bytes on the bus): the "
                             "replay holds no images yet")
        a = cfg.algo
        self.sac = SAC(model, SACSettings(
            gamma=a.gamma, tau=a.tau, lr=cfg.train.lr, init_alpha=a.init_alpha,
            target_entropy=None if a.target_entropy == "auto" else float(a.target_entropy),
            critic_hidden=tuple(cfg.policy.hidden)))
        self.per_sample = batches_per_sample(cfg.replay.batch_size, info.layout.size,
                                             cfg.policy.chunk * info.action_dim)
        self.model.warmup.fill_(float(cfg.replay.learning_starts > 0))  # uniform actions until learning starts
        self.replay: Any = None  # ReplayLink (connect)
        self.debt = 0.0  # gradient steps owed (algo.utd per env step), the fraction carried between updates
        self.sent = 0  # transitions sent to the replay
        self.env_steps = self.gradient_steps = 0  # since learning started
        self.acked = 0  # the replay's count by its last answer (ReplayRequest.acked), across restarts

    def collector(self, max_pending: int, max_staleness: int, count: Callable[[str, float], None]) -> Any:
        return ReplayCollector(self.cfg.algo, max_pending, not self.cfg.algo.keep_utd, count)

    def connect(self, replay: Any) -> None:
        self.replay = replay
        replay.acked = max(replay.acked, self.acked)

    def stop(self) -> None:
        if self.replay is not None:
            self.replay.close()

    @property
    def optimizer(self) -> Optimizers:
        return Optimizers([self.sac.actor_opt, self.sac.critic_opt, self.sac.alpha_opt])

    def learn(self, items: list, version: int, collector: Any) -> Learned:
        """The new segments to the replay, then the gradient steps they are owed, on minibatches it draws."""
        if self.replay is None:
            raise RuntimeError("sac learns from a replay: connect() one first")
        rows = _rows([transitions(seg) for seg in items]) if items else None
        new_steps = int(sum(int(seg.steps.sum()) for seg in items))
        if self.model.obs_norm is not None and items:  # the actor's statistics take in the new observations
            self.model.obs_norm.merge(self.model.obs_norm.sums(torch.from_numpy(rows["obs"])))
        self.sent += len(rows["rewards"]) if rows else 0
        if self.sent >= self.cfg.replay.learning_starts:
            self.model.warmup.fill_(0.0)  # the weights this update publishes act with the actor
            self.env_steps += new_steps
            self.debt += self.cfg.algo.utd * new_steps
        owed = int(self.debt)
        self.debt -= owed
        sums: dict[str, tuple[float, int]] = {}
        done, skipped = self.steps_from_replay(rows, owed, sums)
        self.debt += owed - done  # an empty replay (restarted without its file) owes them on
        out: dict[str, float] = {"batch_size": float(sum(len(seg.obs) for seg in items))}
        out.update({key: total / n for key, (total, n) in sums.items()})
        out.update(gradient_steps=float(done), steps_skipped=skipped)
        versions = np.concatenate([seg.versions for seg in items]) if items else None
        if versions is not None:
            staleness = version - versions
            out.update(staleness_mean=float(staleness.mean()), staleness_max=float(staleness.max()))
        return Learned(out, versions)

    def steps_from_replay(self, rows: dict[str, np.ndarray] | None, owed: int,
                          sums: dict[str, tuple[float, int]]) -> tuple[int, float]:
        """Send ``rows``, then take ``owed`` gradient steps on minibatches the replay draws, asking for the next
        sample before stepping on the one in hand; (steps taken, steps skipped)."""
        size, per = self.cfg.replay.batch_size, self.per_sample
        counts = [per] * (owed // per) + ([owed % per] if owed % per or not owed else [])
        pending = [self.replay.send(rows, counts[0], size)]
        done, skipped = 0, 0.0
        for i, n in enumerate(counts):
            if i + 1 < len(counts):
                pending.append(self.replay.send(None, counts[i + 1], size))
            batch = self.replay.wait(*pending.pop(0))
            for j in range(n if len(batch) else 0):
                with devices.autocast(self.device, self.cfg.policy.dtype):  # policy.dtype = "bfloat16": as PPO's
                    step = self.sac.step(batch.part(j, size))
                skipped += step.pop("steps_skipped")
                for key, value in step.items():  # a skipped step reports fewer numbers: each averaged over its own
                    total, k = sums.get(key, (0.0, 0))
                    sums[key] = (total + value, k + 1)
                done += 1
        self.gradient_steps += done
        return done, skipped

    def extra_state(self) -> dict[str, torch.Tensor]:
        state = self.sac.state()
        tensors = {f"critics.{k}": v for k, v in state["critics"].items()}
        tensors.update({f"targets.{k}": v for k, v in state["targets"].items()})
        tensors["log_alpha"] = state["log_alpha"].reshape(1)
        acked = self.replay.acked if self.replay is not None else self.acked
        tensors["counts"] = torch.tensor([self.sent, self.env_steps, self.gradient_steps, acked], dtype=torch.int64)
        tensors["debt"] = torch.tensor([self.debt], dtype=torch.float64)
        return tensors

    def load_extra_state(self, tensors: dict[str, torch.Tensor]) -> None:
        missing = {"log_alpha", "counts", "debt"} - set(tensors)
        if missing:
            raise ValueError(f"no {', '.join(sorted(missing))}: not a SAC checkpoint")
        critics = {k[len("critics."):]: v for k, v in tensors.items() if k.startswith("critics.")}
        targets = {k[len("targets."):]: v for k, v in tensors.items() if k.startswith("targets.")}
        self.sac.critics.load_state_dict(critics)  # RuntimeError where they do not fit
        self.sac.targets.load_state_dict(targets)
        with torch.no_grad():
            self.sac.log_alpha.copy_(tensors["log_alpha"].reshape(()))
        self.sent, self.env_steps, self.gradient_steps, self.acked = (int(x) for x in tensors["counts"].tolist())
        self.debt = float(tensors["debt"].item())
        if self.replay is not None:
            self.replay.acked = self.acked
        if self.sent >= self.cfg.replay.learning_starts:
            self.model.warmup.fill_(0.0)

    def metrics(self) -> dict[str, float]:
        return {"train/gradient_steps_total": float(self.gradient_steps),
                "train/utd": self.gradient_steps / self.env_steps if self.env_steps else 0.0,
                "train/alpha": self.sac.alpha, "train/replay_sent": float(self.sent)}


def _rows(parts: list[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """Transitions of several segments as one set of rows."""
    return {name: np.concatenate([part[name] for part in parts]) for name in FIELDS}
