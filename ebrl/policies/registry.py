"""``policy.kind``'s registry: a registered name or a user's own class as ``"pkg.module:MyPolicy"``.

A kind is a :class:`~ebrl.policies.base.ChunkPolicy` subclass; :data:`KINDS` names EBRL's as ``"module:Class"``
strings, imported on first use (a kind with heavy dependencies, the VLA's transformers, costs nothing unless a
run uses it). The class owns its facts: how it is built from the ``[policy]`` section (``from_config``), its
latents (``latent_shape_of``), whether it needs the env's action bounds (``needs_bounds``), the algorithms that
can train it (``trained_by``), the ``policy.backbone`` values it reads (``backbones``) and whether generation may
capture its forward as a CUDA graph (``capturable``).

Two places must know a few of those facts without importing any policy (torch costs a second at every simulator
start): the config's check (``algo.name`` against ``trained_by``, ``policy.backbone``) and the simulator's
message bounds (the latents, ``ebrl.sizes``). :data:`KNOWN` holds them for the registered kinds, copied from
their classes (tests/test_policy_registry.py checks every copy); any other kind, a user's or one not listed
there, is asked by importing its class: in the launcher's preflight (:func:`preflight`, before any service
starts) and wherever its latents are needed. Adding a kind is its module, a line in :data:`KINDS` (and,
optionally, in :data:`KNOWN`) and its tests.
"""

from __future__ import annotations

import difflib
from typing import TYPE_CHECKING, Any, NamedTuple

from ebrl.plugins import named_class

if TYPE_CHECKING:
    from ebrl.policies.base import ChunkPolicy

# policy.kind -> "module:Class"; imported when a run uses it
KINDS: dict[str, str] = {
    "mlp": "ebrl.policies.mlp:ChunkGaussianMLP",
    "cnn": "ebrl.policies.cnn:ChunkGaussianCNN",
    "flow": "ebrl.policies.flow:FlowPolicy",
    "squashed": "ebrl.policies.squashed:ChunkSquashedMLP",
    "vla": "ebrl.policies.vla:VLAPolicy",
}

ON_POLICY = frozenset({"ppo", "grpo"})  # the default trained_by: a stochastic actor with a value head
CONV = ("conv",)  # the default backbones: policy.backbone's default, which every kind accepts


class Known(NamedTuple):
    """A registered kind's facts that code building no policy needs, known without importing it."""

    trained_by: frozenset[str]  # the class's trained_by
    backbones: tuple[str, ...]  # the class's backbones
    chunk_latents: bool  # latent_shape_of: [K, A], one value per action of the chunk (True), or none (False)

    def latent_shape(self, chunk: int, action_dim: int) -> tuple[int, ...]:
        return (chunk, action_dim) if self.chunk_latents else (0,)


KNOWN: dict[str, Known] = {
    "mlp": Known(ON_POLICY, CONV, False),
    "cnn": Known(ON_POLICY, CONV, False),
    "flow": Known(ON_POLICY, (*CONV, "transformer"), True),
    "squashed": Known(frozenset({"sac"}), CONV, False),
}


def policy_class(kind: str) -> type[ChunkPolicy]:
    """The class ``policy.kind`` names: a registered name or ``"module:Class"``, imported now. ValueError naming
    ``policy.kind`` where it is neither, does not import, or is not a ChunkPolicy subclass."""
    from ebrl.policies.base import ChunkPolicy

    return named_class("policy.kind", kind, KINDS, ChunkPolicy)


def name_problem(kind: str) -> str | None:
    """What is wrong with ``policy.kind = kind`` as a name, found without importing anything (None: nothing):
    it must be a registered kind or ``"module:Class"``."""
    module, colon, attr = kind.partition(":")
    if kind in KINDS or (colon and module and attr):
        return None
    close = difflib.get_close_matches(kind, KINDS, n=1)
    hint = f" (did you mean {close[0]!r}?)" if close else ""
    return (f"policy.kind = {kind!r}: not one of {', '.join(KINDS)}, nor your own as \"pkg.module:Class\" (an "
            f"ebrl.policies.base.ChunkPolicy subclass){hint}")


def canonical(kind: str) -> str:
    """``kind`` as checkpoints record it: a registered kind's name also where the config names its class."""
    return next((name for name, target in KINDS.items() if target == kind), kind)


def latent_shape(policy_cfg: Any, action_dim: int) -> tuple[int, ...]:
    """The latents per decision of the policy ``policy_cfg`` (a PolicySection) describes: from :data:`KNOWN`
    without importing it, else its class's ``latent_shape_of``."""
    known = KNOWN.get(canonical(policy_cfg.kind))
    if known is not None:
        return known.latent_shape(policy_cfg.chunk, action_dim)
    return tuple(policy_class(policy_cfg.kind).latent_shape_of(policy_cfg, action_dim))


def facts_problem(policy_cfg: Any, algo_name: str, known: Known) -> str | None:
    """What stops the policy ``policy_cfg`` describes (its kind's facts ``known``) from being trained by
    ``algo.name = algo_name`` or from reading its ``policy.backbone`` (None: nothing)."""
    if problem := algorithm_problem(policy_cfg.kind, known.trained_by, algo_name):
        return problem
    if policy_cfg.backbone not in known.backbones:
        return (f"policy.backbone = {policy_cfg.backbone!r}: policy.kind = {policy_cfg.kind!r} reads "
                f"{' or '.join(map(repr, known.backbones))} (its class's backbones)")
    return None


def algorithm_problem(kind: str, trained_by: frozenset[str], algo_name: str) -> str | None:
    """Why ``algo.name = algo_name`` cannot train ``policy.kind = kind``, whose class is ``trained_by`` those
    algorithms (None: it can). A user's algorithm (``"module:Class"``) is not checked: it says what it trains."""
    if ":" in algo_name or algo_name in trained_by:
        return None
    others = [name for name, facts in KNOWN.items() if algo_name in facts.trained_by]
    return (f"algo.name = {algo_name!r} with policy.kind = {kind!r}: that kind is trained by "
            f"{', '.join(sorted(trained_by)) or 'no registered algorithm'} (its class's trained_by), not "
            f"{algo_name}; use policy.kind = {' or '.join(map(repr, others)) or 'a kind it trains'}, or "
            f"algo.name = {' or '.join(map(repr, sorted(trained_by))) or 'your own'}")


def trained_by_problem(model: ChunkPolicy, algo_name: str) -> str | None:
    """:func:`algorithm_problem` of a built policy (what a learner checks before it trains one)."""
    return algorithm_problem(model.kind, frozenset(type(model).trained_by), algo_name)


def known_facts(cls: type[ChunkPolicy], chunk_latents: bool = False) -> Known:
    """A class's facts as :class:`Known` holds them (``chunk_latents``: what its latents are, which only its
    ``latent_shape_of`` says for a given config)."""
    return Known(frozenset(cls.trained_by), tuple(cls.backbones), chunk_latents)


def config_problem(policy_cfg: Any, algo_name: str) -> str | None:
    """The config's check of ``[policy]`` against ``algo.name``, importing nothing: the name, then, for a kind
    in :data:`KNOWN`, its facts. Any other kind is checked by :func:`preflight`."""
    if problem := name_problem(policy_cfg.kind):
        return problem
    known = KNOWN.get(canonical(policy_cfg.kind))
    return facts_problem(policy_cfg, algo_name, known) if known is not None else None


def preflight(policy_cfg: Any, algo_name: str) -> str | None:
    """The launcher's check, before any service starts, of a kind the config could not check without importing
    it (a user's ``"module:Class"``, a registered kind not in :data:`KNOWN`): that its class imports and is a
    ChunkPolicy, and its facts. None: nothing wrong (a kind in KNOWN, checked with the config, is not imported)."""
    if canonical(policy_cfg.kind) in KNOWN:
        return None
    try:
        cls = policy_class(policy_cfg.kind)
    except ValueError as exc:
        hint = " (the module must be importable by the run's processes: installed, or on PYTHONPATH)" \
            if ":" in policy_cfg.kind else ""
        return f"{exc}{hint}"
    return facts_problem(policy_cfg, algo_name, known_facts(cls))
