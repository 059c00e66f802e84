"""SAC behind the algorithm interface (``ebrl.algos.algorithm``): segments into a replay, gradient steps from it.

Each update takes the new decisions (``train.batch_size`` of them; with ``algo.keep_utd = false``, all that
arrived), adds them to the replay (``ebrl.algos.replay``), and runs ``algo.utd`` gradient steps per env step
they hold (:class:`~ebrl.algos.sac.SAC`, each on ``replay.batch_size`` transitions drawn uniformly), once the replay
holds ``replay.learning_starts``; until then generation acts uniformly within the action bounds (the actor's
``warmup`` buffer, published with its weights), as Stable-Baselines3 does. The ratio is kept on average, not per update: the fraction left over carries
to the next. ``train/utd`` reports the ratio achieved so far.

Whether simulators wait for training is the schedule's (``ebrl.sched.modes``): with ``algo.keep_utd`` (the
default) generation holds a group back when its next iteration is more than ``algo.max_staleness`` updates ahead
of training, as for PPO, so the ratio holds and simulators slow down when training cannot keep up; without it
they never wait, every update learns from all that arrived and the ratio drops. Data is never dropped for being
stale: off-policy learning is what a replay is for.

The replay lives in the train process (its stats are ``replay/*``). With ``replay.save`` it is written beside a
checkpoint (at most every ``replay.save_every_s``, and as the run ends) and read back when train restarts; what a
restart could not read back (what arrived after the replay's last save, or all of it without a file) is counted
in ``replay/lost``, never dropped silently.
"""

from __future__ import annotations

import logging
import os
import time
from typing import Any, Callable

import numpy as np
import psutil
import torch

from ebrl import devices
from ebrl.algos.algorithm import Algorithm, Learned, Optimizers
from ebrl.algos.ppo import SegmentCollector
from ebrl.algos.replay import ReplayBuffer
from ebrl.algos.sac import SAC, SACSettings

log = logging.getLogger(__name__)

REPLAY_FILE = "replay.npz"  # RUN_DIR: the replay's transitions as of the newest checkpoint (replay.save)
HOST_MEMORY_SHARE = 0.8  # most of the host's available memory a replay may take (replay.max_bytes = 0)
NEVER_STALE = 1 << 62  # an off-policy collector's staleness bound: none


def replay_bound(max_bytes: int) -> float:
    """The bytes a replay may take: ``replay.max_bytes``, and never more than :data:`HOST_MEMORY_SHARE` of what
    the host has available now."""
    host = HOST_MEMORY_SHARE * psutil.virtual_memory().available
    return min(host, max_bytes) if max_bytes > 0 else host


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

    def __init__(self, model: Any, cfg: Any, info: Any, telemetry: Any, device: torch.device):
        super().__init__(model, cfg, info, telemetry, device)
        if getattr(model, "kind", "") != "squashed":
            raise ValueError("algo.name = 'sac' needs policy.kind = 'squashed' (a tanh-squashed Gaussian actor)")
        a, replay = cfg.algo, cfg.replay
        self.sac = SAC(model, SACSettings(
            gamma=a.gamma, tau=a.tau, lr=cfg.train.lr, init_alpha=a.init_alpha,
            target_entropy=None if a.target_entropy == "auto" else float(a.target_entropy),
            critic_hidden=tuple(cfg.policy.hidden)))
        self.replay = ReplayBuffer(info.layout.size, cfg.policy.chunk * info.action_dim, replay.capacity,
                                   replay_bound(replay.max_bytes))
        self.model.warmup.fill_(float(replay.learning_starts > 0))  # uniform actions until learning starts
        self.rng = np.random.default_rng(cfg.run.seed)
        self.debt = 0.0  # gradient steps owed (algo.utd per env step), the fraction carried between updates
        self.env_steps = self.gradient_steps = self.sampled = 0  # since learning started
        self.held_at_checkpoint = 0  # transitions the newest checkpoint says the replay held (replay/lost)
        self.lost = 0
        self.saved_at = -float("inf")  # when the replay was last written (replay.save_every_s)
        self.rates: tuple[float, int, int] = (time.time(), 0, 0)  # (when, inserted, sampled) at the last report
        log.info("replay of %d transitions (%.1f MiB)", replay.capacity, self.replay.nbytes / 2**20)

    def collector(self, max_pending: int, max_staleness: int, count: Callable[[str, float], None]) -> Any:
        return ReplayCollector(self.cfg.algo, max_pending, not self.cfg.algo.keep_utd, count)

    @property
    def optimizer(self) -> Optimizers:
        return Optimizers([self.sac.actor_opt, self.sac.critic_opt, self.sac.alpha_opt])

    def learn(self, items: list, version: int, collector: Any) -> Learned:
        """The new segments into the replay, then the gradient steps they are owed."""
        new_steps = 0
        for seg in items:
            self.replay.add(seg)  # shapes checked as the learner took the segment
            new_steps += int(seg.steps.sum())
        if self.model.obs_norm is not None and items:  # the actor's statistics take in the new observations
            self.model.obs_norm.merge(self.model.obs_norm.sums(torch.from_numpy(
                np.concatenate([seg.obs for seg in items]))))
        versions = np.concatenate([seg.versions for seg in items]) if items else None
        out: dict[str, float] = {"batch_size": float(sum(len(seg.obs) for seg in items))}
        if self.replay.size >= self.cfg.replay.learning_starts:
            self.model.warmup.fill_(0.0)  # the weights this update publishes act with the actor
            self.env_steps += new_steps
            self.debt += self.cfg.algo.utd * new_steps
        steps, sums, skipped = int(self.debt), {}, 0.0
        self.debt -= steps
        for _ in range(steps):
            with devices.autocast(self.device, self.cfg.policy.dtype):  # policy.dtype = "bfloat16": as PPO's
                step = self.sac.step(self.replay.sample(self.cfg.replay.batch_size, self.rng))
            skipped += step.pop("steps_skipped")
            for key, value in step.items():  # a skipped step reports fewer numbers: each averaged over its own
                total, n = sums.get(key, (0.0, 0))
                sums[key] = (total + value, n + 1)
        self.gradient_steps += steps
        self.sampled += steps * self.cfg.replay.batch_size
        out.update({key: total / n for key, (total, n) in sums.items()})
        out.update(gradient_steps=float(steps), steps_skipped=skipped)
        if versions is not None:
            staleness = version - versions
            out.update(staleness_mean=float(staleness.mean()), staleness_max=float(staleness.max()))
        return Learned(out, versions)

    def extra_state(self) -> dict[str, torch.Tensor]:
        state = self.sac.state()
        tensors = {f"critics.{k}": v for k, v in state["critics"].items()}
        tensors.update({f"targets.{k}": v for k, v in state["targets"].items()})
        tensors["log_alpha"] = state["log_alpha"].reshape(1)
        tensors["counts"] = torch.tensor([self.replay.size, self.env_steps, self.gradient_steps, self.sampled],
                                         dtype=torch.int64)
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
        held, self.env_steps, self.gradient_steps, self.sampled = (int(x) for x in tensors["counts"].tolist())
        self.held_at_checkpoint, self.debt = held, float(tensors["debt"].item())

    def save_data(self, run_dir: str, final: bool) -> None:
        """The replay, with the checkpoint as the run ends and otherwise at most every ``replay.save_every_s``:
        the whole replay is written each time (a full 1,000,000 transitions of HalfCheetah are about 180 MB)."""
        if self.cfg.replay.save and (final or time.time() - self.saved_at >= self.cfg.replay.save_every_s):
            self.replay.save(os.path.join(run_dir, REPLAY_FILE))
            self.saved_at = time.time()

    def restore_data(self, run_dir: str) -> str | None:
        """The replay as the newest checkpoint left it; what it could not read back is counted lost."""
        path, held = os.path.join(run_dir, REPLAY_FILE), self.held_at_checkpoint
        if not held:
            return None
        why = "replay.save is off"
        if self.cfg.replay.save and os.path.exists(path):
            try:
                restored = self.replay.restore(path)
            except (ValueError, OSError, KeyError) as exc:
                why = f"{path} unreadable ({exc})"
            else:
                if lost := max(0, held - restored):  # a file older than the checkpoint (written apart)
                    self.lost = lost
                    self.telemetry.count("replay/lost", lost)
                return f"replay restored: {restored} transitions from {path}"
        elif self.cfg.replay.save:
            why = f"{path} is missing"
        self.lost = held
        self.telemetry.count("replay/lost", held)
        log.warning("replay: the %d transitions it held at the last checkpoint are lost: %s", held, why)
        return f"replay lost {held} transitions ({why})"

    def metrics(self) -> dict[str, float]:
        now, inserted, sampled = time.time(), self.replay.inserted, self.sampled
        then, inserted0, sampled0 = self.rates
        self.rates = (now, inserted, sampled)
        dt = max(now - then, 1e-9)
        return {"replay/size": float(self.replay.size), "replay/capacity": float(self.replay.capacity),
                "replay/bytes": float(self.replay.nbytes), "replay/inserted": float(inserted),
                "replay/sampled": float(sampled), "replay/insert_rate": (inserted - inserted0) / dt,
                "replay/sample_rate": (sampled - sampled0) / dt, "train/gradient_steps_total": float(self.gradient_steps),
                "train/utd": self.gradient_steps / self.env_steps if self.env_steps else 0.0,
                "train/alpha": self.sac.alpha}
