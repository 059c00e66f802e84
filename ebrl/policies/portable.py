"""A trained policy on its own: ``ebrl.load_policy(path)`` rebuilds it from a checkpoint and acts one step at a time.

What ``path`` may be:

- a ``.safetensors`` file (``RUN_DIR/policy.safetensors``, ``RUN_DIR/best.safetensors``, a training
  checkpoint's ``policy.safetensors``, a copy anywhere);
- a training checkpoint directory (``RUN_DIR/checkpoints/v00000040/``): its ``policy.safetensors``;
- a run directory: its *latest* policy, the newer (by version) of ``policy.safetensors`` (written when the run
  ends) and the latest training checkpoint (a run still going, or one that crashed). ``which="best"`` takes
  ``best.safetensors``, the policy the eval service scored best. Latest is the default because it is what the
  run reports and what training continues from; ``best`` was chosen on the evaluation seeds, so a score measured
  again on those same seeds flatters it.

The checkpoint's metadata (``ebrl.policies.checkpoint.portable_metadata``) says how to rebuild the model: its
``[policy]`` section (a user's kind as ``"pkg.module:MyPolicy"``, imported again, and its options), the
observation layout and shape, the action bounds; and which environment it acts in
(``[env]`` as the run resolved it), so :meth:`PortablePolicy.make_env` builds that. A checkpoint written before
that metadata existed is refused with a message saying so, unless ``config`` (the run's ``config.toml``, or a
:class:`~ebrl.config.Config`) is given; a run directory's own ``config.toml`` is used for it automatically.
"""

from __future__ import annotations

import dataclasses
import json
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch

from ebrl import config as config_mod
from ebrl.envs import dictobs
from ebrl.envs.obs import ObsLayout
from ebrl.envs.spec import EnvSpec
from ebrl.policies import make_policy
from ebrl.policies.base import ChunkPolicy
from ebrl.policies.checkpoint import FORMAT, PORTABLE, load_checkpoint, read_metadata

POLICY_FILE = "policy.safetensors"
BEST_FILE = "best.safetensors"
CHECKPOINTS = "checkpoints"
Which = Literal["latest", "best"]


class PolicyFileError(ValueError):
    """A path that holds no loadable policy; the message says what was looked for."""


class PortablePolicy:
    """A policy rebuilt from its checkpoint, acting one step at a time.

    ``action, _ = predict(obs)`` gives one action per call, as Stable-Baselines3's ``predict`` does: the policy
    computes a chunk of K actions from one observation and hands them out in order, computing the next chunk
    once the last is spent (open loop, exactly as training executed them). ``reset()`` (or ``predict``'s
    ``episode_start``) at an episode's start drops what is left of the chunk.
    ``obs`` may be one observation or a batch ``[B, *obs_shape]`` (B environments in lockstep; ``reset(i)``
    resets env i alone). A Dict-observation env's policy also takes the Dict the env itself returns (one, a list,
    or a Dict of batched values), converted as training saw it (:mod:`ebrl.envs.dictobs`). Actions are clipped to
    the action bounds.

    ``deterministic=True``: the Gaussian policies' mean; the flow policy's chain from the fixed initial noise
    x_0 = 0 without the final step's noise. ``deterministic=False`` samples, from a generator seeded by
    ``reset(seed=...)`` (reproducible episode by episode) or by ``load_policy(seed=...)``.
    """

    def __init__(self, model: ChunkPolicy, metadata: dict[str, str], path: str, seed: int = 0):
        self.model = model.eval()
        self.metadata = metadata
        self.path = path
        self.kind, self.chunk, self.action_dim = model.kind, model.chunk, model.action_dim
        self.layout: ObsLayout = model.layout
        self.obs_shape = tuple(json.loads(metadata["obs_shape"]))
        self.action_low = np.asarray(json.loads(metadata["action_low"]), np.float32)
        self.action_high = np.asarray(json.loads(metadata["action_high"]), np.float32)
        self.env_config: dict[str, Any] = json.loads(metadata["env"])
        self.policy_config: dict[str, Any] = json.loads(metadata["policy"])
        self.version = int(metadata["version"]) if metadata.get("version", "").isdigit() else None
        self.generator = torch.Generator().manual_seed(seed)
        self._actions: np.ndarray | None = None  # [B, K, A]: the current chunk of each env
        self._next = np.zeros(0, np.int64)  # [B]: index of each env's next action in its chunk (K: spent)

    def __repr__(self) -> str:
        version = f" v{self.version}" if self.version is not None else ""
        return (f"PortablePolicy({self.kind}{version}, chunk {self.chunk}, env {self.env_config.get('id')!r}, "
                f"from {self.path})")

    # --- acting ---

    def predict(self, obs: Any, state: Any = None, episode_start: Any = None,
                deterministic: bool = True) -> tuple[np.ndarray, None]:
        """The next action ``[A]`` for one observation, or ``[B, A]`` for a batch, and the recurrent state, in
        Stable-Baselines3's form (``action, _ = policy.predict(obs)``). The state is always None: what the
        policy carries from call to call, the rest of each env's chunk, it keeps itself, so ``state`` is
        ignored. ``episode_start`` (a bool, or one per env): those envs start an episode with this observation,
        so their chunk is dropped first, as ``reset(i)`` does. Unlike Stable-Baselines3, ``deterministic``
        defaults to True (evaluation)."""
        batch, single = self._as_batch(obs)
        n = len(batch)
        if self._actions is None or len(self._actions) != n:  # first call, or another number of envs
            self._actions = np.zeros((n, self.chunk, self.action_dim), np.float32)
            self._next = np.full(n, self.chunk, np.int64)
        if episode_start is not None:
            self._next[np.broadcast_to(np.asarray(episode_start, bool).reshape(-1), (n,))] = self.chunk
        spent = self._next >= self.chunk
        if spent.any():
            self._actions[spent] = self.predict_chunk(batch[spent], deterministic)
            self._next[spent] = 0
        actions = self._actions[np.arange(n), self._next]
        self._next += 1
        return (actions[0] if single else actions), None

    def predict_chunk(self, obs: Any, deterministic: bool = True) -> np.ndarray:
        """A whole chunk ``[B, K, A]`` for a batch of observations (clipped to the bounds); no chunk state."""
        batch, _ = self._as_batch(obs)
        chunk = self.model.predict_chunk(batch, deterministic, generator=self.generator)
        return np.clip(chunk, self.action_low, self.action_high)

    def reset(self, index: int | None = None, seed: int | None = None) -> None:
        """An episode starts (of env ``index``, or of every env): its next ``predict`` computes a new chunk.
        ``seed`` re-seeds the sampling of ``deterministic=False``."""
        if index is None:
            self._next[:] = self.chunk
        elif index < len(self._next):
            self._next[index] = self.chunk
        if seed is not None:
            self.generator.manual_seed(seed)

    def _as_batch(self, obs: Any) -> tuple[np.ndarray, bool]:
        if isinstance(obs, Mapping) or (isinstance(obs, (list, tuple)) and obs and isinstance(obs[0], Mapping)):
            return dictobs.pack_batch(self.layout, obs)  # the Dict a Dict-observation env returns (or a batch)
        o = np.asarray(obs, dtype=np.float32)
        if o.shape == self.obs_shape:
            return o.reshape(1, -1), True
        if o.shape[1:] == self.obs_shape:
            return o.reshape(len(o), -1), False
        if o.size == self.layout.size:
            return o.reshape(1, -1), True
        raise ValueError(f"observation of shape {o.shape}: this policy takes {self.obs_shape} (or a batch "
                         f"[B, {', '.join(map(str, self.obs_shape))}])")

    # --- its environment ---

    @property
    def env_spec(self) -> EnvSpec:
        """The environment the policy was trained in (``[env]`` as the run resolved it), without the synthetic
        step latency a scheduler experiment may have added."""
        env = self.env_config
        return EnvSpec(id=env["id"], backend=env.get("backend", "gymnasium"),
                       max_episode_steps=int(env.get("max_episode_steps", 0)), kwargs=dict(env.get("kwargs", {})),
                       obs_keys=tuple(env.get("obs_keys", ())))

    def make_env(self, render_mode: str | None = None):
        """A gymnasium env of the task the policy was trained on, built as EBRL builds it (``ebrl.envs``);
        ``render_mode="rgb_array"`` makes ``env.render()`` return frames."""
        from ebrl.envs.backends import make_env
        from ebrl.envs.render import with_rendering

        spec = self.env_spec
        return make_env(with_rendering(spec) if render_mode == "rgb_array" else spec)


def load_policy(path: str | os.PathLike, *, which: Which = "latest", config: Any = None, device: str = "cpu",
                seed: int = 0) -> PortablePolicy:
    """The policy at ``path``, on ``device``, rebuilt from the checkpoint's metadata (no config needed).

    ``path``: a ``.safetensors`` file (``RUN_DIR/policy.safetensors``, ``RUN_DIR/best.safetensors``, a copy
    anywhere), a training checkpoint directory (its ``policy.safetensors``) or a run directory: its latest policy,
    the newer of ``policy.safetensors`` and the latest checkpoint; ``which="best"`` takes ``best.safetensors``,
    the version the eval service scored best. ``config``: a :class:`~ebrl.config.Config` or the path of a run's
    ``config.toml``, needed only for checkpoints written before policies were portable. ``seed`` seeds the
    sampling of ``predict(obs, deterministic=False)``."""
    file = resolve(path, which)
    metadata = read_metadata(str(file))
    if config is None and not all(key in metadata for key in PORTABLE):
        run_config = Path(path) / "config.toml"
        if Path(path).is_dir() and run_config.is_file():
            config = str(run_config)
    if not all(key in metadata for key in PORTABLE):
        if config is None:
            raise PolicyFileError(
                f"{file} was written before EBRL policies carried their config (no {', '.join(PORTABLE)} in its "
                "metadata); give the run's config: ebrl.load_policy(path, config='RUN_DIR/config.toml') or "
                "`ebrl eval PATH --config RUN_DIR/config.toml`")
        from ebrl.envs import describe
        from ebrl.policies.checkpoint import portable_metadata

        cfg = config if isinstance(config, config_mod.Config) else config_mod.load(str(config))
        metadata = {**metadata, **portable_metadata(cfg.policy, cfg.env, describe(EnvSpec.from_config(cfg.env)))}
    policy = from_metadata(metadata, device=device, seed=seed, source=str(file))
    load_checkpoint(policy.model, str(file))
    return policy


def from_metadata(metadata: dict[str, str], *, device: str = "cpu", seed: int = 0, source: str = "") -> PortablePolicy:
    """A policy with fresh weights built from a portable checkpoint's ``metadata`` (load the weights next)."""
    if metadata.get("format") != FORMAT:
        raise PolicyFileError(f"{source or 'policy'}: policy format {metadata.get('format')!r}; this EBRL reads "
                              f"{FORMAT!r}")
    policy_cfg = _policy_section(json.loads(metadata["policy"]), source)
    layout = ObsLayout.from_dict(json.loads(metadata["layout"]))
    bounds = (np.asarray(json.loads(metadata["action_low"]), np.float64),
              np.asarray(json.loads(metadata["action_high"]), np.float64))
    try:  # a user's kind ("pkg.module:MyPolicy") is imported again: its module must be importable here
        model = make_policy(dataclasses.replace(policy_cfg, checkpoint=""), layout, int(metadata["action_dim"]),
                            bounds)
    except (ImportError, ValueError) as exc:
        raise PolicyFileError(f"{source or 'policy'}: cannot rebuild its policy: {exc}") from None
    return PortablePolicy(model.to(device), metadata, source, seed=seed)


def resolve(path: str | os.PathLike, which: Which = "latest") -> Path:
    """The policy file ``path`` names (see the module's docstring); PolicyFileError says what is missing."""
    p = Path(path)
    if p.is_file():
        return p
    if not p.is_dir():
        raise PolicyFileError(f"{p}: no such file or directory")
    is_run = (p / "config.toml").is_file() or (p / CHECKPOINTS).is_dir()
    if not is_run:
        if (p / POLICY_FILE).is_file():  # a training checkpoint's directory
            return p / POLICY_FILE
        raise PolicyFileError(f"{p}: neither a run directory (config.toml, checkpoints/) nor a checkpoint "
                              f"directory ({POLICY_FILE})")
    if which == "best":
        if not (p / BEST_FILE).is_file():
            raise PolicyFileError(f"{p}: no {BEST_FILE} (the run had no eval service, eval.every = 0, or none "
                                  "finished an evaluation)")
        return p / BEST_FILE
    from ebrl.algos import checkpoint

    candidates = [f for f in (p / POLICY_FILE, _checkpoint_policy(checkpoint.latest(p))) if f is not None and f.is_file()]
    if not candidates:
        raise PolicyFileError(f"{p}: no policy yet ({POLICY_FILE} is written when the run ends, "
                              f"{CHECKPOINTS}/ every train.checkpoint_every updates)")
    return max(candidates, key=_version)  # the first of equal versions: policy.safetensors


def _checkpoint_policy(directory: Path | None) -> Path | None:
    return None if directory is None else directory / POLICY_FILE


def _version(file: Path) -> int:
    try:
        return int(read_metadata(str(file)).get("version", -1))
    except (ValueError, OSError):
        return -1


def _policy_section(values: dict[str, Any], file: str) -> config_mod.PolicySection:
    """The ``[policy]`` section alone, checked as a section: not against a default config's other sections (its
    ``algo.name`` is not the one that trained the policy)."""
    try:
        section = config_mod.make_section("policy", config_mod.PolicySection, values)
        section.check()
        return section
    except config_mod.ConfigError as exc:
        raise PolicyFileError(f"{file}: its [policy] metadata does not fit this EBRL: {exc}") from None
