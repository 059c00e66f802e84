"""Dict observations: any gymnasium env whose observation space is a ``Dict`` (nested too) as EBRL's flat
observation and its :class:`~ebrl.envs.obs.ObsLayout`, with no wrapper written by the user.

Each leaf of the Dict, named by its key path (``"camera/front"``), becomes one field of the layout, of the kind
its space says:

- a uint8 ``Box`` of shape (H, W, C), C in 1, 3 or 4: an ``image`` field, channel-first (C, H, W), in [0, 1];
- any other ``Box``, a ``Discrete`` (its value), ``MultiDiscrete`` or ``MultiBinary``: a ``vector`` field,
  flattened; the policies concatenate every vector field into their state input;
- a ``Text``: a ``tokens`` field of :data:`~ebrl.envs.obs.INSTRUCTION_TOKENS` ids (:func:`~ebrl.envs.obs.tokenize`).

``env.obs_keys`` selects and orders the leaves (a key path of an inner Dict selects every leaf under it); empty:
every leaf, in the Dict's own order (gymnasium sorts a plain dict's keys). The field names are the key paths, so
the layout alone converts an observation Dict (:func:`pack`, :func:`pack_batch`): a trained policy's ``predict``
takes the Dict the env returns. Goal-conditioned envs (gymnasium-robotics) report ``info["is_success"]``; the
adapter passes it on as EBRL's ``info["success"]`` too.

Images travel on the bus as their bytes (``ObsField.uint8``; :meth:`~ebrl.envs.obs.ObsLayout.to_wire`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import gymnasium as gym
import numpy as np

from ebrl.envs.obs import INSTRUCTION_TOKENS, ObsField, ObsLayout, tokenize
from ebrl.envs.spec import EnvError

SUPPORTED = ("a uint8 Box (H, W, C) with C in 1, 3, 4 (an image), any other Box, Discrete, MultiDiscrete, "
             "MultiBinary (numbers), Text (an instruction)")
_NUMBERS = (gym.spaces.Box, gym.spaces.Discrete, gym.spaces.MultiDiscrete, gym.spaces.MultiBinary)


def is_image(space: gym.Space) -> bool:
    return (isinstance(space, gym.spaces.Box) and space.dtype == np.uint8 and len(space.shape) == 3
            and space.shape[2] in (1, 3, 4))


def leaves(space: gym.spaces.Dict, prefix: str = "") -> dict[str, gym.Space]:
    """Every leaf of a (nested) Dict space by key path, in the Dict's order."""
    out: dict[str, gym.Space] = {}
    for key, sub in space.spaces.items():
        path = f"{prefix}{key}"
        if isinstance(sub, gym.spaces.Dict):
            out.update(leaves(sub, path + "/"))
        else:
            out[path] = sub
    return out


def field_of(path: str, space: gym.Space, env_id: str) -> ObsField:
    """The layout field of one leaf; EnvError naming the leaf and what is supported for any other space."""
    if is_image(space):
        height, width, channels = space.shape
        return ObsField(path, "image", (channels, height, width), uint8=True)  # bytes / 255: uint8 on the bus
    if isinstance(space, gym.spaces.Text):
        return ObsField(path, "tokens", (INSTRUCTION_TOKENS,))
    if isinstance(space, _NUMBERS):
        return ObsField(path, "vector", (max(1, int(np.prod(space.shape))),))
    raise EnvError(f"{env_id}: observation key {path!r} has the space {space}, which EBRL cannot read; a Dict "
                   f"observation's leaves may be {SUPPORTED}")


def layout_of(space: gym.spaces.Dict, keys: Sequence[str] = (), env_id: str = "env") -> ObsLayout:
    """The layout of a Dict observation space, of the leaves ``keys`` select (all when empty), in their order."""
    found = leaves(space)
    if not found:
        raise EnvError(f"{env_id}: the observation space {space} is an empty Dict")
    chosen: list[str] = []
    for key in keys or list(found):
        under = [p for p in found if p == key or p.startswith(key.rstrip("/") + "/")]
        if not under:
            raise EnvError(f"env.obs_keys: {env_id} has no observation key {key!r}; its keys: "
                           f"{', '.join(map(repr, found))}")
        chosen += [p for p in under if p not in chosen]
    return ObsLayout(tuple(field_of(p, found[p], env_id) for p in chosen))


def lookup(obs: Mapping, path: str) -> Any:
    """The value at key path ``path`` of a (nested) observation Dict; KeyError naming the path when absent."""
    node: Any = obs
    rest = path
    while True:
        if not isinstance(node, Mapping):
            raise KeyError(f"observation has no key {path!r} (a {type(node).__name__} where a Dict was expected)")
        if rest in node:
            return node[rest]
        head, sep, rest = rest.partition("/")
        matches = [k for k in node if str(k) == head]
        if not sep or not matches:
            raise KeyError(f"observation has no key {path!r} (keys here: {', '.join(map(str, node))})")
        node = node[matches[0]]


def _part(field: ObsField, value: Any, batch: int | None) -> np.ndarray:
    """One field's values as floats, ``[*field.shape]`` (``batch`` None) or ``[batch, *field.shape]``."""
    lead = () if batch is None else (batch,)
    if field.kind == "tokens":
        texts = [value] if batch is None else list(value)
        if not all(isinstance(t, str) for t in texts) or len(texts) != (batch or 1):
            raise ValueError(f"observation key {field.name!r} is text; got {type(value).__name__}")
        return np.stack([tokenize(t, field.size) for t in texts]).reshape(*lead, *field.shape).astype(np.float32)
    array = np.asarray(value)
    if array.dtype.kind not in "biuf":
        raise ValueError(f"observation key {field.name!r} holds {array.dtype} values, not numbers")
    if field.kind == "image":
        channels, height, width = field.shape
        if array.shape != (*lead, height, width, channels):
            raise ValueError(f"observation key {field.name!r} is an image of shape {array.shape}; its space says "
                             f"{(*lead, height, width, channels)} (H, W, C)")
        # an image's values are bytes: a wider integer or float array's are clipped to them (NaN stays, for the guard)
        return np.clip(np.moveaxis(array, -1, -3).astype(np.float32), 0, 255) / np.float32(255)
    if array.size != (batch or 1) * field.size:
        raise ValueError(f"observation key {field.name!r} has {array.size} values; its space says {field.size}"
                         + (f" per env ({batch} envs)" if batch is not None else ""))
    return array.astype(np.float32).reshape(*lead, *field.shape)


def pack(layout: ObsLayout, obs: Mapping) -> np.ndarray:
    """One observation Dict as the flat float32 vector of ``layout`` (whose field names are key paths)."""
    if not isinstance(obs, Mapping):
        raise ValueError(f"expected an observation Dict, got {type(obs).__name__}")
    return layout.pack({f.name: _part(f, lookup(obs, f.name), None) for f in layout.fields})


def pack_batch(layout: ObsLayout, obs: Mapping | Sequence[Mapping]) -> tuple[np.ndarray, bool]:
    """One observation Dict, a list of them, or a Dict of batched values (``[B, ...]`` arrays, lists of texts, as
    a vector env returns) as flat observations ``[B, layout.size]``, and whether it was a single one."""
    if not isinstance(obs, Mapping):
        return np.stack([pack(layout, o) for o in obs]), False
    values = {f.name: lookup(obs, f.name) for f in layout.fields}
    batch = _batch_size(layout, values)
    if batch is None:
        return pack(layout, obs)[None], True
    parts = [_part(f, values[f.name], batch).reshape(batch, -1) for f in layout.fields]
    return np.concatenate(parts, axis=1), False


def _batch_size(layout: ObsLayout, values: dict[str, Any]) -> int | None:
    """How many envs a Dict of values holds: None for a single observation (images (H, W, C), one text, vectors of
    one observation's size); ValueError for values that disagree."""
    sizes = set()
    for f in layout.fields:
        value = values[f.name]
        if f.kind == "tokens":
            sizes.add(None if isinstance(value, str) else len(value))
        elif f.kind == "image":
            shape = np.shape(value)
            sizes.add(shape[0] if len(shape) == 4 else None)
        else:
            size = int(np.size(value))
            sizes.add(None if size == f.size else size // f.size)
    batched = sizes - {None}
    if len(batched) > 1:
        raise ValueError(f"observation Dict holds different numbers of envs per key ({sorted(batched)})")
    if not batched:
        return None
    # a key whose single value has the size of one env (a vector of size 1 with one env) reads as batched too
    return batched.pop()


class DictObservation(gym.ObservationWrapper):
    """A Dict-observation env as a flat Box-observation one with ``obs_layout`` (``make_env`` adds it)."""

    def __init__(self, env: gym.Env, keys: Sequence[str] = (), env_id: str = "env"):
        super().__init__(env)
        self.env_id = env_id
        self.obs_layout = layout_of(env.observation_space, keys, env_id)
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, (self.obs_layout.size,), np.float32)

    def step(self, action: Any) -> tuple[Any, ...]:
        """A step, with gymnasium-robotics' ``info["is_success"]`` also as EBRL's ``info["success"]``."""
        obs, reward, terminated, truncated, info = super().step(action)
        if "is_success" in info and "success" not in info:
            info = {**info, "success": bool(info["is_success"])}
        return obs, reward, terminated, truncated, info

    @property
    def skip_observation(self) -> bool:  # an env that renders lazily (ebrl.envs.backends.lazy_observer)
        return self.env.unwrapped.skip_observation

    @skip_observation.setter
    def skip_observation(self, value: bool) -> None:
        self.env.unwrapped.skip_observation = value

    def observe(self) -> np.ndarray:
        return self.observation(self.env.unwrapped.observe())

    def observation(self, observation: Any) -> np.ndarray:
        try:
            return pack(self.obs_layout, observation)
        except (KeyError, ValueError) as exc:
            raise EnvError(f"{self.env_id}: {exc.args[0] if exc.args else exc}") from None
