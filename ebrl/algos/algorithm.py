"""The algorithm interface and its registry: what a learning algorithm brings to a learner (``algo.name``).

The learner (``ebrl.algos.learner``) and the train service are the same for every algorithm: they take segments
in, judge them (``ebrl.algos.intake``), keep versions honest, publish weights, write checkpoints and refuse bad
numbers. An :class:`Algorithm` brings the rest:

* its **collector** (:meth:`Algorithm.collector`): the bounded intake of segments it learns from. An on-policy
  algorithm's hands each update the oldest ``train.batch_size`` decisions and drops those too stale; an
  off-policy one's hands the new decisions, which its update puts into a replay buffer;
* its **model** beyond the policy (critics, target networks, a temperature), its optimizer(s) and its update,
  :meth:`Algorithm.learn`, which returns the update's numbers;
* its **state** for checkpoints: :attr:`Algorithm.optimizer` (several optimizers look like one:
  :class:`Optimizers`), :meth:`Algorithm.generators` and the tensors beyond the policy
  (:meth:`Algorithm.extra_state`). An algorithm that learns from a replay (:attr:`Algorithm.uses_replay`) gets
  the run's replay service (``ebrl/services/replay.py``) through :meth:`Algorithm.connect`.

``algo.name`` is one of :data:`ALGORITHMS` or a user's own class as ``"my_pkg.module:MyAlgo"``. Adding one is its
module, a line in :data:`ALGORITHMS` and its tests (docs/algorithms.md, with SAC as the worked example).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Callable, ClassVar

import numpy as np

from ebrl.plugins import named_class

if TYPE_CHECKING:
    import torch

    from ebrl.meter import Telemetry
    from ebrl.policies.base import ChunkPolicy

# algo.name -> "module:Class"; imported when a run uses it
ALGORITHMS: dict[str, str] = {
    "ppo": "ebrl.algos.onpolicy:PPOAlgorithm",
    "grpo": "ebrl.algos.onpolicy:GRPOAlgorithm",
    "sac": "ebrl.algos.offpolicy:SACAlgorithm",
}
OFF_POLICY = frozenset({"sac"})  # registered algorithms with uses_replay (known without importing them)


@dataclass
class Learned:
    """One update's outcome: its numbers (``train/<name>`` stats; ``steps_skipped`` and ``decisions_dropped`` are
    counted, not reported) and the acting versions of the decisions it learned from (the staleness histogram)."""

    stats: dict[str, float]
    versions: np.ndarray | None = None


class Algorithm:
    """The base of every algorithm: a learner makes one with the policy it trains and the run's config."""

    name: ClassVar[str] = ""
    data_parallel: ClassVar[bool] = False  # supports train.world_size > 1 (ebrl.algos.parallel)
    uses_replay: ClassVar[bool] = False  # learns from the replay service: the run has one (OFF_POLICY)

    def __init__(self, model: ChunkPolicy, cfg: Any, info: Any, telemetry: Telemetry, device: torch.device):
        """``model``: the policy (on ``device``); ``cfg``: the run's config; ``info``: the env's
        (``obs_shape``, ``action_dim``, ``bounds``, ``layout``)."""
        self.model, self.cfg, self.info, self.telemetry, self.device = model, cfg, info, telemetry, device

    def collector(self, max_pending: int, max_staleness: int, count: Callable[[str, float], None]) -> Any:
        """The bounded intake: ``add(segment)``, ``take(version, batch_size)``, ``ready_steps``,
        ``pending_steps``, ``segments()`` (what a stopping learner hands over), ``size(item)``."""
        raise NotImplementedError

    def join(self, dp: Any) -> None:
        """With several ranks (``data_parallel`` algorithms): take the gradient steps through ``dp``'s wrapped
        policy and optimizer (``ebrl.algos.parallel.DataParallel``)."""
        raise ValueError(f"algo.name = {self.name!r} trains on one rank: set train.world_size = 1")

    def connect(self, replay: Any) -> None:
        """Where :attr:`uses_replay`: the replay to learn from, before the first update (the train service's
        :class:`~ebrl.algos.replaylink.ReplayLink`)."""

    def stop(self) -> None:
        """Training stops: an update waiting on what the algorithm awaits (the replay) ends, from any thread."""

    def prepare(self) -> None:
        """Costly set-up to do once the first weights are out (the train service calls it on the update thread)."""

    def learn(self, items: list, version: int, collector: Any) -> Learned:
        """One update on ``items`` (what ``collector.take`` gave; maybe none on a data-parallel rank)."""
        raise NotImplementedError

    @property
    def optimizer(self) -> Any:
        """What a checkpoint saves and restores as the optimizer: ``state_dict``, ``load_state_dict``, ``state``."""
        raise NotImplementedError

    def generators(self) -> dict[str, torch.Generator]:
        """Random generators of its own, saved with checkpoints (torch's global one always is)."""
        return {}

    def extra_state(self) -> dict[str, torch.Tensor]:
        """Tensors a restart needs beyond the policy and the optimizer (critics, targets...)."""
        return {}

    def load_extra_state(self, tensors: dict[str, torch.Tensor]) -> None:
        """Take back :meth:`extra_state`; ValueError where they do not fit."""
        if tensors:
            raise ValueError(f"{self.name} keeps no state beyond its policy and optimizer; the checkpoint has "
                             f"{sorted(tensors)[:3]}")

    def reset_moments(self) -> None:
        """Forget the optimizers' moments (after an update that made non-finite weights was undone)."""
        self.optimizer.state.clear()

    def metrics(self) -> dict[str, float]:
        """Stats of its own beyond the update's numbers (a replay's size and rates)."""
        return {}


def algorithm_class(name: str) -> type[Algorithm]:
    """The class ``algo.name`` names: a registered name or ``"module:Class"``. ValueError naming what is wrong."""
    return named_class("algo.name", name, ALGORITHMS, Algorithm)


def uses_replay(name: str) -> bool:
    """Whether the algorithm ``algo.name`` names learns from a replay (then the run has a replay service); a
    registered one without importing it, a user's ``module:Class`` by its class."""
    return name in OFF_POLICY if name in ALGORITHMS else algorithm_class(name).uses_replay


class Optimizers:
    """Several optimizers as one for checkpoints: one ``state_dict`` with the parameters numbered across them in
    order (as one optimizer numbers its groups'), ``load_state_dict`` splitting it back."""

    def __init__(self, optimizers: list[torch.optim.Optimizer]):
        self.optimizers = optimizers

    @property
    def state(self) -> Any:
        return _States(self.optimizers)

    def state_dict(self) -> dict[str, Any]:
        state: dict[int, Any] = {}
        groups: list[dict[str, Any]] = []
        offset = 0
        for opt in self.optimizers:
            sd = opt.state_dict()
            state.update({offset + index: slots for index, slots in sd["state"].items()})
            groups += [{**group, "params": [offset + p for p in group["params"]]} for group in sd["param_groups"]]
            offset += sum(len(group["params"]) for group in sd["param_groups"])
        return {"state": state, "param_groups": groups}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        groups, state = list(state_dict["param_groups"]), state_dict["state"]
        mine = [len(opt.param_groups) for opt in self.optimizers]
        if len(groups) != sum(mine):
            raise ValueError(f"{len(groups)} parameter groups for optimizers of {sum(mine)}")
        parts, offset = [], 0
        for opt, n in zip(self.optimizers, mine):
            own, groups = groups[:n], groups[n:]
            indices = [int(p) for group in own for p in group["params"]]
            if indices != list(range(offset, offset + len(indices))):
                raise ValueError("parameter numbering does not fit these optimizers")
            parts.append({"state": {int(i) - offset: state[i] for i in state if offset <= int(i) < offset + len(indices)},
                          "param_groups": [{**g, "params": [int(p) - offset for p in g["params"]]} for g in own]})
            offset += len(indices)
        for opt, part in zip(self.optimizers, parts):  # the numbering of all checked before any loads
            opt.load_state_dict(part)


class _States:
    """The optimizers' ``state`` as one: ``clear`` clears every one's."""

    def __init__(self, optimizers: list[torch.optim.Optimizer]):
        self.optimizers = optimizers

    def clear(self) -> None:
        for opt in self.optimizers:
            opt.state.clear()

    def __len__(self) -> int:
        return sum(len(opt.state) for opt in self.optimizers)
