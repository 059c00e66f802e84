"""TOML config -> validated, typed config. Errors name the field; unknown keys are errors.

Each section is a dataclass that checks what its own values mean (:meth:`Section.check`), in the module of the
part of the run it configures: :mod:`~ebrl.config.run` (``[run]``, ``[bus]``, ``[hosts]``),
:mod:`~ebrl.config.rollout` (``[env]``, ``[sim]``, ``[policy]``, ``[gen]``), :mod:`~ebrl.config.training`
(``[algo]``, ``[train]``, ``[replay]``, ``[alloc]``) and :mod:`~ebrl.config.observers` (``[viz]``, ``[log]``,
``[eval]``). The few rules that tie sections together are :mod:`~ebrl.config.schema`'s, beside :class:`Config`
itself; reading and writing files is :mod:`~ebrl.config.files`. Every field has a docstring (``doc``), shown by
``ebrl config`` and docs/reference/config.md. Values derived from several fields are computed in one place
(properties of :class:`Config`). Everything a caller uses is importable from ``ebrl.config``.
"""

from ebrl.config.base import ConfigError, Section, doc, parse_slowdown
from ebrl.config.files import (STOCK_DIRS, apply_override, copy_stock, describe, dump_toml, find, from_dict, load,
                               make_section, override, read, stock_configs)
from ebrl.config.observers import EvalSection, LogSection, VizSection
from ebrl.config.rollout import BACKEND_NAMES, EnvSection, GenSection, PolicySection, SimSection
from ebrl.config.run import ROLES, BusSection, HostEntry, RunSection
from ebrl.config.schema import SECTIONS, Config, processes, train_ranks, vectorized
from ebrl.config.training import AlgoSection, AllocSection, ReplaySection, TrainSection

__all__ = ["BACKEND_NAMES", "ROLES", "SECTIONS", "STOCK_DIRS", "AlgoSection", "AllocSection", "BusSection", "Config",
           "ConfigError", "EnvSection", "EvalSection", "GenSection", "HostEntry", "LogSection", "PolicySection",
           "ReplaySection", "RunSection", "Section", "SimSection", "TrainSection", "VizSection", "apply_override",
           "copy_stock", "describe", "doc", "dump_toml", "find", "from_dict", "load", "make_section", "override",
           "parse_slowdown", "processes", "read", "stock_configs", "train_ranks", "vectorized"]
