"""TOML config -> validated, typed config. Errors name the field; unknown keys are errors.

Each section is a dataclass that checks what its own values mean (:meth:`Section.check`); the few rules
that tie sections together are :func:`_check_across`. Every field has a docstring (``doc``), shown by
``ebrl config`` and docs/reference/config.md. Values derived from several fields are computed in one place
(properties of :class:`Config`).
"""

from __future__ import annotations

import dataclasses
import difflib
import ipaddress
import os
import tomllib
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar, Literal

import tomli_w

from ebrl import devices, typecheck
from ebrl.envs import records
from ebrl.presets import PRESETS
from ebrl import graph, keys


class ConfigError(ValueError):
    """A config that cannot be used; the message names the field."""


def doc(text: str, default: Any = dataclasses.MISSING, factory: Any = dataclasses.MISSING) -> Any:
    if factory is not dataclasses.MISSING:
        return field(default_factory=factory, metadata={"doc": text})
    return field(default=default, metadata={"doc": text})


class Section:
    """A ``[section]`` of the config. Its types are checked as it is read; :meth:`check` then checks what its
    values mean, each section its own rules (:attr:`POSITIVE` fields and :meth:`_check`); the few rules that
    tie sections together are :func:`_check_across`."""

    NAME: ClassVar[str] = ""
    POSITIVE: ClassVar[tuple[str, ...]] = ()  # fields that must be > 0

    def check(self) -> None:
        for key in self.POSITIVE:
            value = getattr(self, key)
            if not value > 0:  # NaN too
                raise ConfigError(f"{self.NAME}.{key} = {value}: must be > 0")
        self._check()

    def _check(self) -> None:
        """The section's rules beyond its positive fields."""


@dataclass
class RunSection(Section):
    NAME = "run"
    POSITIVE = ("stats_interval",)

    name: str = doc("run name; part of every bus key, so two runs never see each other", "quickstart")
    mode: Literal["ebrl", "colocated", "hybrid", "async"] = doc(
        "ebrl: every mechanism; colocated: all envs step together, then train; hybrid: sim/gen pipelined "
        "across groups, barrier before training; async: rollout and training overlap on disjoint cores, "
        "batch-synchronous stepping", "ebrl")
    iterations: int = doc("training updates (policy versions) after which the run ends; 0 runs until Ctrl-C", 100)
    target_return: float | None = doc(
        "end the run early once the mean return of the last 20 episodes training took (train/episode_return_mean, "
        "as training reports it) reaches this; absent: never", None)
    target_success: float | None = doc(
        "end the run early once the success rate of the last 20 episodes training took (train/success_rate, tasks "
        "that report success) reaches this fraction (0.9: 90 %); absent: never", None)
    seed: int = doc("seed for environments and model initialisation", 0)
    output_dir: str = doc("where run directories (logs, resolved config, summary) are created", "runs")
    group: str = doc("a Unix group whose members may read the run's directory (mode 0750, that group); empty: "
                     "only you (mode 0700: the logs, config, stats and policy of a run are its owner's)", "")
    stall_timeout: float = doc(
        "seconds a stage may stop moving (a service's stats reports, env steps, answered observations, updates) "
        "before the launcher says which and why, restarts it, and ends the run if that does not help "
        "(ebrl/stall.py); each stage is watched from its first progress on; 0: off", 30.0)
    stats_interval: float = doc("seconds between stats reports of each service", 1.0)
    startup_timeout: float = doc("seconds to wait for every service to come up", 120.0)
    log_level: Literal["debug", "info", "warning"] = doc("log level of the services", "info")
    slowdown: str = doc("inject a slowdown for experiments: \"<service>=<factor>@<seconds>\" stretches every busy "
                        "span of that service by factor (CPU busy-wait) from that many seconds after it started, "
                        "e.g. \"train=1.3@30\"; empty: none", "")
    restart: Literal["on-failure", "never"] = doc(
        "a service that dies is started again (on-failure, with backoff, at most max_restarts times per service) "
        "or the run stops (never)", "on-failure")
    max_restarts: int = doc("most restarts of one service before the run stops", 3)
    processes: list[list[str]] | Literal["auto"] = doc(
        "services that share one process on their host, e.g. [[\"sim\", \"gen\", \"train\"]]: the messages between "
        "them never leave it (one bus session, no router hop, no socket), each keeps its own stats, lanes, token "
        "and rights, and a process that dies is started again with every service in it. A simulator that shares "
        "a process shares its memory: the env's code can then reach the others (docs/processes.md). Empty: each "
        "service in a process of its own. \"auto\": sim, gen and train in one process on a host with a GPU that "
        "runs all three (one training rank, no allocator) with a GPU simulator EBRL ships (env.backend = \"mjwarp\", "
        "its own task); on a CPU host, sim and gen in one process where the run is the ebrl mode without the "
        "allocator, each env a worker process of its own (not sim.vectorized) and no module:EnvId of yours; else "
        "each alone; decided at start, written into the run's config.toml", "auto")

    def _check(self) -> None:
        try:
            keys.check_chunk(self.name, "run.name")
        except ValueError as exc:
            raise ConfigError(str(exc)) from None
        if self.target_success is not None and not 0.0 < self.target_success <= 1.0:
            raise ConfigError(f"run.target_success = {self.target_success}: a fraction in (0, 1] (0.9: 90 %)")
        if self.iterations < 0 or self.max_restarts < 0:
            raise ConfigError(f"run.iterations ({self.iterations}) and run.max_restarts ({self.max_restarts}) must "
                              "be >= 0")
        seen: set[str] = set()
        for group in [] if self.processes == "auto" else self.processes:
            if len(group) < 2:
                raise ConfigError(f"run.processes: {group}: a shared process holds at least two services")
            for role in group:
                if role not in ROLES:
                    raise ConfigError(f"run.processes: unknown service {role!r}; services are {', '.join(ROLES)}")
                if role in seen:
                    raise ConfigError(f"run.processes: {role} is named twice; a service runs in one process")
                seen.add(role)
        if self.slowdown:
            try:
                parse_slowdown(self.slowdown)
            except ValueError as exc:
                raise ConfigError(f"run.slowdown = {self.slowdown!r}: {exc}") from None


@dataclass
class BusSection(Section):
    NAME = "bus"

    mode: Literal["peer", "client"] = doc(
        "how services meet: client (each a client of its host's launcher, which routes and, with bus.auth, takes "
        "from each only what its role may send: one identity per role) or peer (a mesh: services talk directly, "
        "a few percent faster on message-heavy runs, and trust each other's credentials; observers still only "
        "read)", "client")
    listen: list[str] = doc(
        "endpoints the launcher listens on; services and scripts connect here (a busy port falls back to a free one)",
        factory=lambda: ["tcp/127.0.0.1:7447"],
    )
    connect: list[str] = doc("extra endpoints to connect to (a Zenoh router or another host)", factory=list)
    config_file: str = doc("path to a native Zenoh JSON5 config (TLS, access control); empty for none", "")
    max_message_bytes: int = doc("a received message larger than this is dropped before it is decoded: by Zenoh "
                                 "(its receive limit) or counted as bus/oversized; each message type has its own "
                                 "lower limit too (schemas/: x-ebrl-max-bytes)", 256 << 20)
    auth: bool = doc("every process of the run signs in with the run's secret (RUN_DIR/bus.secret, 0600): a process "
                     "without it can neither join nor read the bus. false: an open bus that any process on the host "
                     "can join", True)
    secret_file: str = doc("the run's secret file; empty: RUN_DIR/bus.secret, created by the launcher. A run over "
                           "several hosts needs one shared file (create it with `ebrl secret PATH`, copy it to each "
                           "host)", "")
    insecure: bool = doc("allow plain (unencrypted) endpoints that leave this host in bus.listen / bus.connect; "
                         "without it such an endpoint is refused: use tls/... with bus.config_file", False)

    def _check(self) -> None:
        if not self.listen and not self.connect:
            raise ConfigError("bus.listen and bus.connect are both empty: services could not find each other")


BACKEND_NAMES = tuple(records.BACKENDS)  # env.backend's choices: the simulator backends' registry


@dataclass
class EnvSection(Section):
    NAME = "env"

    backend: Literal[BACKEND_NAMES] = doc(f"simulator adapter ({records.described()})", "gymnasium")
    id: str = doc(f"environment id: {records.described_ids()}", "InvertedPendulum-v5")
    max_episode_steps: int = doc("time limit in env steps; 0 keeps the environment's own (LIBERO: the suite's, "
                                 "280/280/300/520/400)", 0)
    kwargs: dict[str, Any] = doc("extra keyword arguments for the environment constructor "
                                 f"({records.described_options()})", factory=dict)
    latency: Literal["none", "lognormal"] = doc(
        "add a synthetic step latency (CPU busy-wait) drawn from this distribution, for scheduler experiments", "none")
    latency_mean_ms: float = doc("mean of the added step latency in milliseconds", 16.0)
    latency_sigma: float = doc("sigma of the lognormal step latency (0.3: mild tail, 0.8: heavy tail)", 0.3)
    max_abs_reward: float = doc(
        "the largest reward magnitude of one env step that training takes: a larger one is clipped to it and a "
        "non-finite one counts as 0 (counted: sim/rewards_clipped, sim/rewards_nonfinite), and train drops a "
        "segment that carries more (train/reward_bound_dropped); inf: no bound", 1e6)
    reward_bound: float | Literal["auto"] = doc(
        "the largest reward magnitude of one env step that an episode may carry and still count toward the "
        "return statistics a run reports and ends on (train/episode_return_mean, run.target_return): an episode "
        "with a larger one is trained on but not counted (train/episodes_past_bound). \"auto\": the env's "
        "declared reward range where it has one (a finite reward_range), else learned from the run's own "
        "rewards: 1000 x the 90th percentile of the per-step magnitude of the first 1,000 nonzero decision "
        "rewards (and of later ones, never lower); an episode with nonzero rewards waits for it to count. inf: no "
        "bound",
        "auto")
    obs_keys: list[str] = doc(
        "a Dict observation's keys the policy sees, in order, as key paths (\"observation\", \"camera/front\"; an "
        "inner Dict's path selects every key under it); empty: all of them. Each becomes a field by its space: a "
        "uint8 (H, W, C) Box an image, other Box, Discrete, MultiDiscrete, MultiBinary a vector, Text "
        "instruction tokens", factory=list)

    def _check(self) -> None:
        if not self.max_abs_reward > 0:  # NaN too
            raise ConfigError(f"env.max_abs_reward = {self.max_abs_reward}: must be > 0 (inf: no bound)")
        if self.reward_bound != "auto" and not self.reward_bound > 0:
            raise ConfigError(f"env.reward_bound = {self.reward_bound}: must be > 0, \"auto\" or inf")


@dataclass
class SimSection(Section):
    NAME = "sim"
    POSITIVE = ("groups", "envs_per_group", "cores_per_env", "segment_length")

    groups: int = doc("environment groups; each publishes its observations on its own key", 2)
    envs_per_group: int = doc("environments per group (one worker process each)", 4)
    cores: list[int] = doc("CPU cores of the simulation budget; empty: every core this process may use", factory=list)
    stepping: Literal["async", "batch"] | None = doc(
        "async: each env steps through its chunk on its own; batch: all envs of a group step, then a barrier; "
        "absent: the mode's choice", None)
    core_rebinding: bool | Literal["auto"] | None = doc(
        "greedy core rebinding of single steps onto free cores (async stepping); false pins each env worker to "
        "one core and runs whole chunks; \"auto\" (the ebrl mode's choice) measures the env steps/s each "
        "delivers in the run's steady state, keeps the faster at 97.5 %, and measures again when the chosen one "
        "falls behind, the step latencies shift, or every 5 minutes; absent: the mode's choice", None)
    cores_per_env: int = doc(
        "cores each env worker is pinned to, every thread of it: 1 for a single-threaded simulator; more for one "
        "that steps on several threads (the sim stats' sim/env_cores_used says how many it keeps busy), whose "
        "workers then run whole chunks on their own sets of cores, without step-level rebinding; with "
        "alloc.enabled the allocator picks it from its profile", 1)
    group_pipeline: bool | None = doc(
        "pipeline groups through generation; false makes all envs one group; absent: the mode's choice", None)
    lazy_render: bool | None = doc(
        "render only the observations the policy reads (the one each chunk ends on, and an episode's last) in "
        "envs that render on demand (robosuite and LIBERO cameras, a lazily rendering Dict env); false renders "
        "every step's, as RLinf's LIBERO env does (its chunk_step steps its vector env once per action and each "
        "step renders the cameras); absent: the mode's choice (ebrl: true; colocated, hybrid, async: false)", None)
    vectorized: bool | Literal["auto"] = doc(
        "each group one process stepping its envs as one batch (ManiSkill on GPU PhysX: one vectorized env of "
        "envs_per_group envs; other backends: envs_per_group copies stepped in turn) instead of one worker process "
        "per env; \"auto\": on where the simulator steps on the GPU (ManiSkill with env.kwargs.sim_backend = "
        "\"physx_cuda\", or \"auto\" on a CUDA host)",
        "auto")
    segment_length: int = doc("chunk decisions per trajectory segment sent to training", 32)
    nice: int = doc("niceness of the sim service and its env workers (0-19): where simulation shares cores with "
                    "generation and training, the scheduler serves those first, so an update finishes sooner and "
                    "less of the data is acted by an older version; 0: equal shares. In a process the sim shares "
                    "with other services (run.processes) only its env workers and vectorized group processes take "
                    "it (groups stepping on a thread of that process do not)", 0)
    step_timeout: float = doc("seconds an env worker may take for one request (a chunk, or one step under batch "
                              "stepping) before it is killed and replaced; 0: automatic, 20x the "
                              "measured P99 chunk latency and at least 20 s (120 s until 50 chunks were seen)", 0.0)

    def _check(self) -> None:
        if not 0 <= self.nice <= 19:
            raise ConfigError(f"sim.nice = {self.nice}: must be 0 (equal shares) to 19 (the lowest priority)")


@dataclass
class PolicySection(Section):
    NAME = "policy"
    POSITIVE = ("chunk", "embed_dim", "denoise_steps", "width", "depth", "heads", "patch")

    kind: str = doc(
        "policy model: mlp (Gaussian chunk from a flat observation), cnn (conv image encoder + proprioception + "
        "instruction embedding, Gaussian chunk), flow (flow-matching action head: the chunk by denoising), squashed "
        "(tanh of a Gaussian with state-dependent std, scaled to the env's action bounds: SAC's actor), vla (a "
        "vision-language-action model on Hugging Face transformers, ebrl.policies.vla), or your own ChunkPolicy "
        "subclass as \"my_pkg.module:MyPolicy\" (docs/policies.md)", "mlp")
    options: dict[str, Any] = doc("kind-specific options, read by the kind's from_config (your own kind's, vla's); "
                                  "the built-in kinds read the fields below", factory=dict)
    chunk: int = doc("K: actions per chunk, executed open-loop", 4)
    hidden: list[int] = doc("hidden layer widths", factory=lambda: [64, 64])
    init_log_std: float = doc("initial log standard deviation of the Gaussian (flow: of the stochastic final "
                              "step)", -0.5)
    channels: list[int] = doc("cnn/flow on images: conv channels per layer of the image encoder",
                              factory=lambda: [16, 32, 32])
    embed_dim: int = doc("cnn/flow: feature width of each observation part (image projection, proprioception, "
                         "instruction embedding)", 32)
    denoise_steps: int = doc("flow: N, denoising (Euler) steps per chunk; cost grows with N, the interface does "
                             "not change", 4)
    backbone: Literal["conv", "transformer"] = doc(
        "flow: the observation encoder: conv (conv image encoder + proprioception + instruction embedding) or "
        "transformer (image patches, proprioception and instruction tokens through a transformer, as VLAs do)",
        "conv")
    width: int = doc("transformer backbone: token width", 256)
    depth: int = doc("transformer backbone: layers (about 12 * width^2 parameters each)", 4)
    heads: int = doc("transformer backbone: attention heads (a divisor of width)", 8)
    patch: int = doc("transformer backbone: image patch side in pixels (a divisor of the image size)", 8)
    dtype: Literal["auto", "float32", "bfloat16"] = doc(
        "precision of generation's forward passes and training's: float32, bfloat16 autocast (matrix products "
        "in bfloat16, reductions and the losses in float32; on GPUs with bfloat16 units, and on CPUs with them, "
        "AVX-512 BF16 or AMX: asked for on a CPU without, the launcher runs float32), or auto: bfloat16 where "
        "generation and training run on a GPU that has it and it measured faster for this policy at the run's "
        "batch sizes, else float32 (decided at start, ebrl.autotune)", "auto")
    normalize_obs: bool = doc("standardise the vector fields of the observation by running mean and variance "
                              "(kept in the policy, updated by training from each batch, shipped with the "
                              "weights); images and tokens pass unchanged", False)
    checkpoint: str = doc("safetensors policy checkpoint to start training from (relative to the working "
                          "directory); empty: fresh weights", "")

    def _check(self) -> None:
        from ebrl.policies.registry import name_problem  # the registry's names only: no policy is imported
        if problem := name_problem(self.kind):
            raise ConfigError(problem)
        if self.width % self.heads:
            raise ConfigError(f"policy.width = {self.width}: must be a multiple of policy.heads = {self.heads}")


@dataclass
class GenSection(Section):
    NAME = "gen"
    POSITIVE = ("threads",)

    max_batch_groups: int = doc("most groups served by one forward pass; 0 means all groups", 0)
    cores: list[int] = doc("cores for the generation process; empty: the mode's choice", factory=list)
    threads: int = doc("torch threads of the generation process", 1)
    device: str = doc("torch device of the policy's forward passes: auto (of the GPU this process is bound to and "
                      "the CPU, the one that measured faster for this policy, precision and batch at start: "
                      "ebrl.autotune; the GPU when nothing measured it), cpu, cuda or cuda:N", "auto")
    compile: Literal["auto", "off", "cudagraphs"] = doc(
        "how the chunk forward runs on a GPU: off (eagerly), cudagraphs (captured once per batch size and "
        "replayed: one launch per batch; for small policies, whose passes are launch-bound), or auto: CUDA graphs "
        "where the capture works and measured faster, else eagerly (decided at start, ebrl.autotune)", "auto")

    def _check(self) -> None:
        _device(self.device, "gen.device")
        if self.compile == "cudagraphs" and self.device == "cpu":
            raise ConfigError("gen.compile = 'cudagraphs' captures CUDA graphs; gen.device is 'cpu' (use \"auto\" or "
                              "a CUDA device, or gen.compile = 'off')")


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


@dataclass
class VizSection(Section):
    NAME = "viz"
    POSITIVE = ("window_s", "port", "web_port")

    rerun: Literal["spawn", "serve", "web", "save", "off"] = doc(
        "live timeline in rerun: spawn a viewer, serve over gRPC for a viewer to connect (even late), web (serve "
        "rerun's web viewer to a browser, on 127.0.0.1:web_port), save only, or off (no viz service); every mode "
        "but off also writes RUN_DIR/timeline.rrd", "off")
    port: int = doc("gRPC port of the rerun server (serve, web; on 127.0.0.1) or of the spawned viewer (spawn)",
                    9876)
    web_port: int = doc("HTTP port of the web viewer's page (web), on 127.0.0.1; reach it from a laptop with "
                        "ssh -L web_port:127.0.0.1:web_port -L port:127.0.0.1:port HOST", 9090)
    memory_limit: str = doc("rerun server memory (serve, web): what a late viewer can still see", "2GiB")
    window_s: float = doc("seconds of history the live Gantt shows while following the present", 20.0)
    spans: bool = doc("publish timeline spans; false keeps only the busy/<lane> stats (for overhead measurements)",
                      True)
    record: bool = doc("record every stats report, span and event of the run to RUN_DIR/stats.msgpack (on the "
                       "primary host of several)", True)
    report: bool = doc("write RUN_DIR/report/ (Gantt PNG, throughput PNG, report.md) when the run ends", True)


@dataclass
class LogSection(Section):
    NAME = "log"
    POSITIVE = ("flush_s",)

    tensorboard: bool = doc("write RUN_DIR/tb/: TensorBoard event files of every metric, every episode's return and "
                            "success, eval results, the config (hparams) and the run's metadata, keyed by env steps "
                            "(open with `tensorboard --logdir runs/`)", True)
    csv: bool = doc("write RUN_DIR/metrics.csv: one row per value (step, wall_time, key, value), the same values "
                    "as TensorBoard", True)
    wandb: bool = doc("log to Weights & Biases (the optional extra: pip install 'ebrl[wandb]'); offline runs go to "
                      "RUN_DIR/wandb/ (upload later with `wandb sync`)", False)
    wandb_project: str = doc("W&B project", "ebrl")
    wandb_entity: str = doc("W&B entity (user or team); empty: your default", "")
    wandb_group: str = doc("W&B group of this run (e.g. a sweep or a seed set); empty: none", "")
    wandb_tags: list[str] = doc("W&B tags of this run", factory=list)
    wandb_mode: Literal["online", "offline"] = doc(
        "online (needs `wandb login` or WANDB_API_KEY, checked before the run starts) or offline (no account "
        "needed)", "online")
    exclude: list[str] = doc("metrics not written by any sink: shell patterns of metric names or of the keys "
                             "written, e.g. [\"cpu/*\", \"proc/*\", \"sim/busy/*\"]", factory=list)
    flush_s: float = doc("seconds between flushes of the sinks to disk", 5.0)


@dataclass
class EvalSection(Section):
    NAME = "eval"

    every: int = doc("evaluate every this many policy versions (v = every, 2 x every, ..., and the final version "
                     "of run.iterations) in the eval service; 0: no eval service. A version published while an "
                     "evaluation runs waits; a newer one replaces it (eval/versions_skipped)", 0)
    episodes: int = doc("episodes per evaluation", 10)
    seeds: int = doc("reset seed of the first evaluation episode; episode i resets with seeds + i, the same for "
                     "every version. The default is far from training's reset seeds (run.seed * 100003 + env + "
                     "7919 x episode), so evaluation runs on held-out initial states", 2_000_000_000)
    deterministic: bool = doc("deterministic actions (the Gaussian mean; flow: initial noise x0 = 0 and no noise at "
                              "the final step); false samples them", True)
    video_episodes: int = doc("episodes of each evaluation recorded to RUN_DIR/videos/v<version>/ (MP4, or GIF "
                              "without an ffmpeg encoder); 0: none", 1)
    cores: list[int] = doc("the eval service's cores: one env worker process pinned to each; empty: one worker on "
                           "any core. Always at idle priority (SCHED_IDLE), so it only takes CPU time training "
                           "leaves", factory=list)
    final_timeout: float = doc("seconds the launcher waits, once run.iterations are done, for the evaluation of "
                               "the final version (the other services idle meanwhile); 0: it does not wait", 300.0)

    def _check(self) -> None:
        if self.every < 0 or self.episodes < 1 or self.video_episodes < 0 or self.final_timeout < 0:
            raise ConfigError(f"[eval]: every ({self.every}), video_episodes ({self.video_episodes}) and "
                              f"final_timeout ({self.final_timeout}) must be >= 0 and episodes ({self.episodes}) >= 1")
        if not 0 <= self.seeds <= 2**32 - 1 - self.episodes:
            raise ConfigError(f"eval.seeds = {self.seeds}: must be in [0, 2^32 - 1 - eval.episodes] (simulators "
                              "take 32-bit seeds)")


ROLES = graph.START_ORDER  # every service a host can run, in start order (ebrl.graph.Role.start)


@dataclass
class HostEntry:
    """One ``[hosts.<name>]`` table: what ``ebrl up CONFIG --host <name>`` starts on that machine."""

    services: list[str] = doc(f"services this host runs, from {', '.join(ROLES)}", factory=list)
    listen: list[str] = doc("bus endpoints this host's launcher listens on (reachable by the other hosts; under "
                            "srun, {primary} and {node} name the primary's node and this one: docs/scaling-out.md); "
                            "empty: bus.listen", factory=list)
    connect: list[str] = doc("bus endpoints this host's launcher connects to (another host's listen endpoint, or "
                             "an `ebrl router`); empty: bus.connect", factory=list)
    cores: list[int] = doc("sim.cores on this host; empty: the config's sim.cores", factory=list)
    ranks: int = doc("training ranks on this host, where it runs train and others do too (ranks are numbered "
                     "across hosts in [hosts] order); 0: an equal share of the train.world_size ranks the other "
                     "entries leave", 0)


SECTIONS: dict[str, type[Section]] = {cls.NAME: cls for cls in (
    RunSection, BusSection, EnvSection, SimSection, PolicySection, GenSection, AlgoSection, TrainSection,
    ReplaySection, AllocSection, VizSection, LogSection, EvalSection)}


@dataclass
class Config:
    run: RunSection = field(default_factory=RunSection)
    bus: BusSection = field(default_factory=BusSection)
    env: EnvSection = field(default_factory=EnvSection)
    sim: SimSection = field(default_factory=SimSection)
    policy: PolicySection = field(default_factory=PolicySection)
    gen: GenSection = field(default_factory=GenSection)
    algo: AlgoSection = field(default_factory=AlgoSection)
    train: TrainSection = field(default_factory=TrainSection)
    replay: ReplaySection = field(default_factory=ReplaySection)
    alloc: AllocSection = field(default_factory=AllocSection)
    viz: VizSection = field(default_factory=VizSection)
    log: LogSection = field(default_factory=LogSection)
    eval: EvalSection = field(default_factory=EvalSection)
    hosts: dict[str, HostEntry] = field(default_factory=dict)  # [hosts.<name>]: which services run where

    @property
    def num_envs(self) -> int:
        """Envs of one sim service (one host)."""
        return self.sim.groups * self.sim.envs_per_group

    @property
    def rollout_length(self) -> int:
        """Chunk decisions of each env per iteration (one policy update consumes one iteration) with one sim
        host; with n live sim hosts, 1/n of it (``Schedule.length``)."""
        return self.train.batch_size // self.num_envs

    def to_dict(self) -> dict[str, dict[str, Any]]:
        return dataclasses.asdict(self)


# Where the stock configs are: inside the package (a clone's configs/ links here).
STOCK_DIRS = (Path(__file__).resolve().parent / "configs",)


def stock_configs() -> dict[str, Path]:
    """The configs that come with EBRL, by name (``quickstart``: ``configs/quickstart.toml``)."""
    found: dict[str, Path] = {}
    for directory in STOCK_DIRS:
        for path in sorted(directory.glob("*.toml")) if directory.is_dir() else ():
            found.setdefault(path.stem, path)
    return found


def find(path_or_name: str | os.PathLike) -> Path:
    """A config file: ``path_or_name`` where it exists, else the stock config of that name (``quickstart`` or
    ``quickstart.toml``); a ConfigError naming the stock configs if neither."""
    path = Path(path_or_name)
    if path.exists() or len(path.parts) > 1:
        return path
    stock = stock_configs()
    if (name := path.name.removesuffix(".toml")) in stock:
        return stock[name]
    raise ConfigError(f"{path_or_name}: no such file, and no stock config of that name (stock configs: "
                      f"{', '.join(stock) or 'none found'}; `ebrl configs` lists them)")


def copy_stock(name: str, directory: str | os.PathLike) -> list[Path]:
    """Copy the stock config ``name`` into ``directory`` to edit, with the configs it is based on (``base``,
    the same relative names), never replacing a file; the files written, the config first."""
    stock = stock_configs()
    if name.removesuffix(".toml") not in stock:
        raise ConfigError(f"no stock config {name!r} (stock configs: {', '.join(stock)})")
    chain, source = [], stock[name.removesuffix(".toml")]
    while source is not None:
        chain.append(source)
        base = tomllib.loads(source.read_text()).get("base")
        source = (source.parent / base).resolve() if isinstance(base, str) else None
    root = chain[0].parent
    targets = [Path(directory) / src.relative_to(root) for src in chain]
    if existing := [str(t) for t in targets if t.exists()]:
        raise ConfigError(f"{', '.join(existing)} already exists; nothing was written")
    for src, target in zip(chain, targets):
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_text(src.read_text())
    return targets


def override(path: str, value: Any) -> str:
    """``section.key=value`` for :func:`load`'s overrides, ``value`` written as TOML (``override("run.name",
    "a")`` is ``run.name="a"``)."""
    return f"{path}={_toml_value(value)}"


def load(path: str | os.PathLike, overrides: list[str] = ()) -> Config:
    """Read ``path`` (a TOML file with its ``base`` files, or a stock config's name: :func:`find`), apply
    ``section.key=value`` overrides, validate."""
    raw = read(find(path))
    for item in overrides:
        apply_override(raw, item)
    return from_dict(raw)


def read(path: str | os.PathLike, _chain: tuple[Path, ...] = ()) -> dict[str, Any]:
    """The raw tables of a config file. A top-level ``base = "other.toml"`` (relative to this file) starts
    from that file's tables: this file's keys replace the base's key by key, section by section (a
    ``[hosts.<name>]`` table as a whole)."""
    try:
        with open(path, "rb") as fh:
            raw = tomllib.load(fh)
    except FileNotFoundError:
        where = f" (the base of {_chain[-1]})" if _chain else ""
        raise ConfigError(f"{path}: no such file{where}") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML: {exc}") from None
    if "base" not in raw:
        return raw
    base = raw.pop("base")
    if not isinstance(base, str) or not base:
        raise ConfigError(f"{path}: base = {base!r}: expected the path of another config file (a string)")
    here = Path(path).resolve()
    base_path = (here.parent / base).resolve()
    if base_path in (*_chain, here):
        cycle = " -> ".join(str(p) for p in (*_chain, here, base_path))
        raise ConfigError(f"{path}: base files form a cycle: {cycle}")
    merged = read(base_path, (*_chain, here))
    for name, table in raw.items():
        if isinstance(table, dict) and isinstance(merged.get(name), dict):
            merged[name] = {**merged[name], **table}
        else:
            merged[name] = table
    return merged


def apply_override(raw: dict[str, Any], item: str) -> None:
    """Apply one ``section.key=value``; the key may go deeper (``env.kwargs.obs=rgb``) and is a TOML dotted key
    (``env.kwargs."a.b"=1``); the value is parsed as TOML, else taken as a string. An empty value
    (``run.target_return=``) removes the key: the field takes its default (``None`` where that means absent)."""
    path, text = [], ""
    for at in (i for i, c in enumerate(item) if c == "="):  # the first "=" outside a quoted key
        try:
            path, text = _key_path(tomllib.loads(f"{item[:at].strip()} = 0")), item[at + 1:]
            break
        except tomllib.TOMLDecodeError:
            continue
    if len(path) < 2:
        raise ConfigError(f"--set {item!r}: expected section.key=value (or section.key.subkey=value)")
    unset = not text.strip()
    try:
        value = tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        value = text
    table = raw
    for depth, key in enumerate(path[:-1]):
        table = table.setdefault(key, {})
        if not isinstance(table, dict):
            where = ".".join(path[:depth + 1])
            raise ConfigError(f"--set {item!r}: {where} is not a table" if depth else
                              f"--set {item!r}: [{where}] is not a section")
    if unset:
        table.pop(path[-1], None)
    else:
        table[path[-1]] = value


def _key_path(parsed: dict[str, Any]) -> list[str]:
    """``{"a": {"b": 0}}`` (one dotted key, parsed) -> ``["a", "b"]``."""
    path = []
    while isinstance(parsed, dict) and len(parsed) == 1:
        key, parsed = next(iter(parsed.items()))
        path.append(key)
    return path


def from_dict(raw: dict[str, Any]) -> Config:
    sections: dict[str, Any] = {}
    for name, value in raw.items():
        if name not in SECTIONS and name != "hosts":
            raise ConfigError(f"unknown section [{name}]; known sections: {', '.join(SECTIONS)}, hosts")
        if not isinstance(value, dict):
            raise ConfigError(f"[{name}] must be a table")
        if name == "hosts":
            sections[name] = _hosts(value)
        else:
            sections[name] = _section(name, SECTIONS[name], value)
    cfg = Config(**sections)
    for name in SECTIONS:
        getattr(cfg, name).check()
    _check_across(cfg)
    return cfg


def _section(name: str, cls: type, values: dict[str, Any]) -> Any:
    hints = typing.get_type_hints(cls)
    known = {f.name for f in dataclasses.fields(cls)}
    for key in values:
        if key not in known:
            close = difflib.get_close_matches(key, sorted(known), n=1)
            hint = f" (did you mean {name}.{close[0]}?)" if close else ""
            raise ConfigError(f"unknown key {name}.{key}{hint}; known keys of [{name}]: {', '.join(sorted(known))}")
    return cls(**{key: typecheck.check(value, hints[key], f"{name}.{key}", ConfigError) for key, value in values.items()})


def _hosts(raw: dict[str, Any]) -> dict[str, HostEntry]:
    hosts = {}
    for name, value in raw.items():
        try:
            keys.check_chunk(name, "host name")
        except ValueError as exc:
            raise ConfigError(f"[hosts.{name}]: {exc}") from None
        if not isinstance(value, dict):
            raise ConfigError(f"[hosts.{name}] must be a table (services, listen, connect, cores)")
        entry = hosts[name] = _section(f"hosts.{name}", HostEntry, value)
        for role in entry.services:
            if role not in ROLES:
                raise ConfigError(f"hosts.{name}.services: unknown service {role!r}; services are {', '.join(ROLES)}")
    if hosts and not any("sim" in entry.services for entry in hosts.values()):
        raise ConfigError("[hosts]: no host runs sim")
    for role in ("train", "gen"):
        owners = [name for name, entry in hosts.items() if role in entry.services]
        if hosts and (len(owners) != 1 if role == "gen" else not owners):
            raise ConfigError(f"[hosts]: {'exactly one host' if role == 'gen' else 'a host'} must run {role} (found "
                              f"{len(owners)}: {', '.join(owners) or 'none'})")
    for name, entry in hosts.items():
        if entry.ranks < 0 or (entry.ranks and "train" not in entry.services):
            raise ConfigError(f"hosts.{name}.ranks = {entry.ranks}: training ranks on a host that runs train (>= 0)")
    return hosts


def train_ranks(cfg: Config) -> dict[str, range]:
    """The training ranks of each ``[hosts]`` entry that runs train, numbered across hosts in table order (the
    first holds rank 0: the primary); one host's: all of them."""
    owners = [name for name, entry in cfg.hosts.items() if "train" in entry.services]
    given = sum(cfg.hosts[name].ranks for name in owners)
    shares = sum(1 for name in owners if not cfg.hosts[name].ranks)  # these split what the others leave
    counts = [cfg.hosts[name].ranks or max(0, cfg.train.world_size - given) // max(1, shares) for name in owners]
    out, first = {}, 0
    for name, count in zip(owners, counts):
        out[name], first = range(first, first + count), first + count
    return out


def _check_train_hosts(cfg: Config) -> None:
    """Training ranks on several hosts: their shares, the rendezvous, what the run lacks for them."""
    ranks = train_ranks(cfg)
    if len(ranks) < 2:
        return
    shares = ", ".join(f"{name}: {len(r)}" for name, r in ranks.items())
    if sum(len(r) for r in ranks.values()) != cfg.train.world_size or any(len(r) == 0 for r in ranks.values()):
        raise ConfigError(f"train.world_size = {cfg.train.world_size}: the hosts that run train hold {shares} "
                          "ranks; give each host at least one and hosts.<name>.ranks that add up to it")
    host, _, port = cfg.train.rendezvous.rpartition(":")
    if not host or not port.isdigit():
        raise ConfigError(f"train.rendezvous = {cfg.train.rendezvous!r}: training on several hosts ({shares}) "
                          "needs HOST:PORT on the primary host where the ranks meet")
    if not cfg.train.trusted_networks:
        raise ConfigError("train.trusted_networks: training on several hosts sends gradients over "
                          "torch.distributed, which has no authentication or encryption of its own; name the "
                          "networks (CIDR) it may use, a private network between the hosts")
    for network in cfg.train.trusted_networks:
        try:
            ipaddress.ip_network(network, strict=False)
        except ValueError as exc:
            raise ConfigError(f"train.trusted_networks: {exc}") from None
    if cfg.alloc.enabled:
        raise ConfigError("alloc.enabled: the allocator plans one host's training; with ranks on several hosts set "
                          "alloc.enabled = false")


def vectorized(cfg: Config) -> bool:
    """Whether each sim group is one vectorized process (``sim.vectorized``; "auto": where physics is on the GPU;
    always for a backend whose group is one batch by nature, MuJoCo Warp's model of many worlds): the backend's
    record decides (``ebrl.envs.records``)."""
    return records.backend_record(cfg.env.backend).vectorized(cfg.sim.vectorized, cfg.env.kwargs)


def _device(text: str, path: str) -> None:
    try:
        devices.check_syntax(text, path)
    except ValueError as exc:
        raise ConfigError(str(exc)) from None


def _check_across(cfg: Config) -> None:
    """The rules that tie sections together (each section checked its own: :meth:`Section.check`)."""
    _check_batching(cfg)
    _check_vectorized(cfg)
    if cfg.sim.cores_per_env > 1 and cfg.sim.core_rebinding is True:
        raise ConfigError(f"sim.cores_per_env = {cfg.sim.cores_per_env}: pins each env worker to a set of cores, "
                          "which sim.core_rebinding = true does not use (rebinding hands out single cores); set "
                          "sim.cores_per_env = 1, or leave sim.core_rebinding to the mode")
    _check_processes(cfg)
    _check_algorithm(cfg)
    _check_train_hosts(cfg)
    if cfg.algo.name == "grpo":
        envs = cfg.num_envs
        if cfg.algo.group_size < 2 or envs % cfg.algo.group_size:
            raise ConfigError(f"algo.group_size = {cfg.algo.group_size}: grpo needs at least 2 rollouts per group "
                              f"and the {envs} envs (sim.groups x sim.envs_per_group) to split into whole groups")
        if not (PRESETS[cfg.run.mode]["overlap"] if cfg.train.overlap is None else cfg.train.overlap):
            raise ConfigError(f"algo.name = \"grpo\" with run.mode = {cfg.run.mode!r}: grpo learns from whole "
                              "episodes, which a rollout -> train barrier of fixed length cannot wait for; use "
                              "run.mode = \"ebrl\" or \"async\" (or train.overlap = true)")


def _check_algorithm(cfg: Config) -> None:
    """The algorithm against the policy it trains and the ranks that train it."""
    from ebrl.policies.registry import config_problem  # a registered kind's facts, no policy imported
    if problem := config_problem(cfg.policy, cfg.algo.name):  # a user's kind: checked by the launcher's preflight
        raise ConfigError(problem)
    if cfg.algo.name == "sac" and cfg.train.world_size > 1:
        raise ConfigError(f"train.world_size = {cfg.train.world_size}: sac trains on one rank (its replay is one "
                          "process's); set train.world_size = 1")


def processes(cfg: Config) -> list[list[str]]:
    """``run.processes`` as lists (``"auto"``, before the launcher decided it: none shared)."""
    return [] if cfg.run.processes == "auto" else cfg.run.processes


def _check_processes(cfg: Config) -> None:
    """``run.processes`` against the services the run has and where they run."""
    shared = {role for group in processes(cfg) for role in group}
    if "train" in shared and cfg.train.world_size > 1:
        raise ConfigError(f"run.processes: train with train.world_size = {cfg.train.world_size}: each training "
                          "rank runs in a process of its own; share a process only with one rank")


def _check_batching(cfg: Config) -> None:
    """An update's batch against the envs that fill it and the ranks that split it."""
    if cfg.train.batch_size % cfg.num_envs:
        raise ConfigError(f"train.batch_size = {cfg.train.batch_size}: must be a multiple of the number of envs "
                          f"(sim.groups x sim.envs_per_group = {cfg.num_envs}); each env runs batch_size / envs "
                          "decisions per iteration")
    if cfg.train.world_size > 1 and cfg.train.batch_size // cfg.train.world_size < cfg.algo.minibatches:
        raise ConfigError(f"train.world_size = {cfg.train.world_size}: each rank's share of train.batch_size "
                          f"({cfg.train.batch_size}) must hold algo.minibatches ({cfg.algo.minibatches}) decisions")


def _check_vectorized(cfg: Config) -> None:
    """What a vectorized group (one process stepping its envs as one batch) cannot do."""
    record = records.backend_record(cfg.env.backend)
    if record.vectorize == "always" and cfg.sim.vectorized is False:
        raise ConfigError(f"sim.vectorized = false: {record.always_vectorized}")
    if not vectorized(cfg):
        return
    if cfg.alloc.enabled:
        raise ConfigError("alloc.enabled: the allocator profiles the simulator as one env per worker process, and "
                          "sim.vectorized runs a group's envs as one batch (GPU PhysX groups are vectorized by "
                          "default); set alloc.enabled = false, or sim.vectorized = false")
    if cfg.sim.cores_per_env > 1:
        raise ConfigError(f"sim.cores_per_env = {cfg.sim.cores_per_env}: pins each env worker to a set of cores, "
                          "which sim.vectorized does not use (a vectorized group runs on the whole budget); set "
                          "sim.cores_per_env = 1")
    if cfg.algo.name == "grpo":
        raise ConfigError("sim.vectorized: grpo needs group-mates reset to the same initial state, which a "
                          "vectorized batch's partial resets cannot promise; set sim.vectorized = false (GPU PhysX "
                          "groups are vectorized by default)")


def parse_slowdown(text: str) -> tuple[str, float, float]:
    """``"train=1.3@30"`` -> ``("train", 1.3, 30.0)``."""
    service, eq, rest = text.partition("=")
    factor, at, after = rest.partition("@")
    if not (eq and at and service):
        raise ValueError('expected "<service>=<factor>@<seconds>", e.g. "train=1.3@30"')
    value, seconds = float(factor), float(after)
    if value < 1 or seconds < 0:
        raise ValueError("the factor must be >= 1 and the seconds >= 0")
    return service.strip(), value, seconds


def dump_toml(cfg: Config) -> str:
    """The resolved config as TOML (what services read and what the run directory keeps), written by tomli-w:
    any key (a dot or a space in ``env.kwargs``) and any value reads back the same. Absent values (None) are
    left out; reading the file gives them back as defaults."""
    return tomli_w.dumps(_drop_none(cfg.to_dict()))


def _drop_none(value: Any) -> Any:
    if isinstance(value, dict):
        return {k: _drop_none(v) for k, v in value.items() if v is not None}
    if isinstance(value, list):
        return [_drop_none(v) for v in value]
    return value


def _toml_value(value: Any) -> str:
    """One value as inline TOML (for ``ebrl config``'s listing)."""
    if isinstance(value, dict):  # tomli-w writes tables as [sections]: inline them here
        return "{" + ", ".join(f"{tomli_w.dumps({k: 0})[:-len(' = 0')].strip()} = {_toml_value(v)}"
                               for k, v in value.items()) + "}"
    if isinstance(value, list):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    return tomli_w.dumps({"v": value})[len("v = "):].strip()


def _type_name(tp: Any) -> str:
    """``int``, ``list[int]``, ``"a" | "b"``, ``bool, optional`` — for ``ebrl config``."""
    args = typing.get_args(tp)
    if typing.get_origin(tp) is Literal:
        return " | ".join(_toml_value(a) for a in args)
    if type(None) in args:
        inner = [a for a in args if a is not type(None)]
        return " | ".join(_type_name(a) for a in inner) + ", optional"
    if typing.get_origin(tp) in (types.UnionType, typing.Union):
        return " | ".join(_type_name(a) for a in args)
    if args:
        return f"{tp.__origin__.__name__}[{', '.join(_type_name(a) for a in args)}]"
    return getattr(tp, "__name__", str(tp))


def describe() -> str:
    """Every section and key with its type, default and docstring (``ebrl config --fields``)."""
    out = []
    for name, cls in (*SECTIONS.items(), ("hosts.<name>", HostEntry)):
        out.append(f"[{name}]")
        hints = typing.get_type_hints(cls)
        for f in dataclasses.fields(cls):
            default = f.default if f.default is not dataclasses.MISSING else f.default_factory()
            tp = _type_name(hints[f.name])
            shown = "absent" if default is None else _toml_value(default)
            out.append(f"  {f.name} ({tp}, default {shown}): {f.metadata['doc']}")
    return "\n".join(out)
