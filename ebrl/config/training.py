"""What training runs: ``[algo]``, ``[train]``, ``[replay]`` and ``[alloc]``."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from ebrl.config.base import ConfigError, doc, Section, _device


@dataclass
class AlgoSection(Section):
    NAME = "algo"
    POSITIVE = ("epochs", "minibatches")

    name: str = doc(
        "learning algorithm: ppo (GAE with a critic), grpo (group-relative advantages over group_size rollouts "
        "from the same initial state, no critic), sac (soft actor-critic over a replay, with policy.kind = "
        "\"squashed\"), or your own as \"my_pkg.module:MyAlgo\" (docs/algorithms.md)", "ppo")
    group_size: int = doc("grpo: rollouts per group; envs env_id // group_size share their reset seeds", 8)
    max_staleness: int = doc("most policy versions between the weights that act and the update that learns, "
                             "when rollout and training overlap", 1)
    decoupled: bool = doc("decoupled PPO for stale data: clip around the proximal policy, weight by "
                          "pi_prox / pi_behave", True)
    behave_weight_cap: float = doc("upper bound of the pi_prox / pi_behave weight", 5.0)
    prox_logp: Literal["recompute", "interpolate"] = doc(
        "decoupled: log pi_prox recomputed by a forward pass over the batch at the start of each update, or "
        "interpolated by version between the behaviour and the current log-prob (no extra pass; AReaL's "
        "log-linear approximation)", "recompute")
    gae_values: Literal["current", "behaviour"] = doc(
        "values in GAE: from the critic the update starts from, one pass over the batch (current; as AReaL), "
        "or those the acting version's critic gave (behaviour; on stale data they mix two critics)", "current")
    gamma: float = doc("discount per env step (a chunk of k steps is discounted by gamma**k)", 0.99)
    gae_lambda: float = doc("GAE lambda", 0.95)
    clip: float = doc("PPO ratio clip", 0.2)
    epochs: int = doc("passes over each batch", 10)
    minibatches: int = doc("minibatches per pass", 4)
    ent_coef: float = doc("entropy bonus coefficient", 0.0)
    vf_coef: float = doc("value loss coefficient", 0.5)
    max_grad_norm: float = doc("ppo, grpo: gradient clipping norm (sac does not clip, as Stable-Baselines3)", 0.5)
    utd: float = doc("sac: gradient steps per env step (the update-to-data ratio), kept on average; train/utd "
                     "reports the ratio achieved", 1.0)
    keep_utd: bool = doc("sac: where training falls behind, simulators wait for it (at most max_staleness updates "
                         "ahead) and the ratio holds; false: they never wait, each update learns from all that "
                         "arrived and the ratio drops", True)
    tau: float = doc("sac: target networks' soft update, Q' <- (1 - tau) Q' + tau Q after each gradient step", 0.005)
    init_alpha: float = doc("sac: the entropy temperature to start from (tuned automatically from there)", 1.0)
    target_entropy: float | Literal["auto"] = doc("sac: the entropy the temperature is tuned toward; auto: minus the "
                                                  "chunk's action values (policy.chunk x action dimensions)", "auto")

    @property
    def uses_replay(self) -> bool:
        """Whether the algorithm learns from a replay (the run then has a replay service: its switch in
        ``ebrl.graph``). ValueError where a user's ``module:Class`` does not import or is no algorithm."""
        from ebrl.algos.algorithm import uses_replay
        return uses_replay(self.name)

    def _check(self) -> None:
        from ebrl.algos.algorithm import ALGORITHMS  # the registry, imported only to check names against it
        if self.name not in ALGORITHMS and ":" not in self.name:
            raise ConfigError(f"algo.name = {self.name!r}: not one of {', '.join(ALGORITHMS)}, nor your own as "
                              "\"module:Class\"")
        if not 0 < self.tau <= 1:
            raise ConfigError(f"algo.tau = {self.tau}: must be in (0, 1]")
        if not (self.utd > 0 and self.init_alpha > 0):
            raise ConfigError(f"algo.utd = {self.utd}, algo.init_alpha = {self.init_alpha}: both must be > 0")
        if not 0 < self.gamma <= 1:
            raise ConfigError(f"algo.gamma = {self.gamma}: must be in (0, 1]")
        if self.max_staleness < 0:
            raise ConfigError(f"algo.max_staleness = {self.max_staleness}: must be >= 0")


@dataclass
class TrainSection(Section):
    NAME = "train"
    POSITIVE = ("batch_size", "lr", "threads", "world_size", "max_pending")

    batch_size: int = doc("chunk decisions per update", 1024)
    lr: float = doc("Adam learning rate", 3e-4)
    device: str = doc("torch device of the updates: auto (the GPU this process is bound to when torch sees one, "
                      "else the CPU), cpu, cuda or cuda:N; ranks spread over the visible GPUs", "auto")
    threads: int = doc("torch threads of the training process", 1)
    max_pending: int = doc("most chunk decisions buffered while an update runs; beyond it the oldest are dropped (counted)", 8192)
    overlap: bool | None = doc("train while rollout goes on (bounded by algo.max_staleness); false restores the "
                               "rollout -> train barrier; absent: the mode's choice", None)
    cores: list[int] = doc("cores for the training process; empty: the mode's choice", factory=list)
    world_size: int = doc("training ranks (processes, a torch.distributed group over gloo): each update's batch is "
                          "split between them", 1)
    parallel: Literal["ddp", "fsdp"] = doc("with world_size > 1: ddp all-reduces gradients (every rank holds the whole "
                                           "model and optimizer); fsdp shards parameters, gradients and optimizer "
                                           "state between the ranks", "ddp")
    checkpoint_every: int = doc("write a checkpoint (policy, optimizer, version, random state) every this many "
                                "updates, and always at the end; 0: only at the end", 10)
    rendezvous: str = doc("HOST:PORT where training ranks on several hosts meet ([hosts] entries that run train): "
                          "an address of the primary host (rank 0's) that the others reach, inside "
                          "train.trusted_networks; under srun HOST may be {primary}. Ranks on one host meet in "
                          "the run's directory instead", "")
    trusted_networks: list[str] = doc("networks (CIDR, e.g. 10.0.0.0/16) that training ranks on several hosts may "
                                      "use: torch.distributed's channel has no authentication or encryption of its "
                                      "own, so a rendezvous or a host without an address inside them is refused",
                                      factory=list)

    def _check(self) -> None:
        _device(self.device, "train.device")
        if self.checkpoint_every < 0:
            raise ConfigError(f"train.checkpoint_every = {self.checkpoint_every}: must be >= 0")
        if self.max_pending < self.batch_size:
            raise ConfigError(f"train.max_pending = {self.max_pending}: must be >= train.batch_size ({self.batch_size})")


@dataclass
class ReplaySection(Section):
    NAME = "replay"
    POSITIVE = ("capacity", "batch_size")

    capacity: int = doc("off-policy (sac): most transitions (chunk decisions) the replay holds; the oldest are "
                        "overwritten first", 1_000_000)
    max_bytes: int = doc("most bytes the replay's arrays may take; a capacity that needs more is refused as training "
                         "starts, with the numbers. 0: 80 % of the memory the host has available then", 0)
    batch_size: int = doc("transitions per gradient step, drawn uniformly from the replay", 256)
    learning_starts: int = doc("transitions the replay holds before the first gradient step", 100)
    save: bool = doc("write the replay beside a checkpoint (RUN_DIR/replay.npz; at most every save_every_s, and as "
                     "the run ends) and read it back when train restarts; what it cannot read back is counted in "
                     "replay/lost; false: a restart starts with an empty replay", True)
    save_every_s: float = doc("save: the least seconds between two writes of the replay (each writes it whole)", 120.0)

    def _check(self) -> None:
        if not self.save_every_s >= 0:
            raise ConfigError(f"replay.save_every_s = {self.save_every_s}: must be >= 0")
        if self.max_bytes < 0 or self.learning_starts < 0:
            raise ConfigError(f"replay.max_bytes = {self.max_bytes}, replay.learning_starts = {self.learning_starts}: "
                              "must be >= 0")


@dataclass
class AllocSection(Section):
    NAME = "alloc"
    POSITIVE = ("window", "patience", "gap", "min_gen_cores", "min_train_cores", "profile_seconds")

    enabled: bool = doc("profile the stages, pick core quotas with Algorithm 1 at start, and re-balance them while "
                        "the run goes on (the allocator service); false keeps the mode's static cores", False)
    gpu_pool: Literal["mps", "mig", "none"] = doc("how GPU shares are enforced: MPS quotas, MIG instances, whole GPUs",
                                                  "none")
    cpu_pool: Literal["numa", "flat"] = doc("keep a stage's cores on one NUMA node (numa) or ignore topology (flat)",
                                            "flat")
    window: int = doc("stats reports in the moving averages of rollout and training throughput", 20)
    gap: float = doc("re-allocate when rollout and training capacity differ by more than this fraction of the "
                     "faster one ...", 0.15)
    patience: int = doc("... for this many consecutive stats reports", 20)
    min_gen_cores: int = doc("fewest cores generation may get", 1)
    min_train_cores: int = doc("fewest cores training may get", 1)
    profile_path: str = doc("stage profile file; empty: <run.output_dir>/profiles/<run.name>.json", "")
    profile_max_age_h: float = doc("re-profile when the stored profile is older than this (hours)", 168.0)
    profile_seconds: float = doc("seconds measured per profile grid point", 1.0)
