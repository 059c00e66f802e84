"""What rollout runs: ``[env]``, ``[sim]``, ``[policy]`` and ``[gen]``."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

from ebrl.config.base import ConfigError, doc, Section, _device
from ebrl.envs import records


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
