"""The sweep file: which config every trial runs, what it varies, the objective, the budget (no Optuna needed).

A sweep file is TOML with a top-level ``config`` (a run config never has one, so either can be given to
``ebrl sweep``); ``--param``, ``--set`` and the other flags add to it or replace its values, and a config given
instead of a sweep file is swept by the flags alone. :func:`check` then loads the config with every param at each
end of its range (each choice), so that a key that is not a config key, or a value the config refuses, is an
error naming the param before any trial starts. docs/sweeps.md describes every key.
"""

from __future__ import annotations

import dataclasses
import difflib
import json
import os
import re
import tomllib
from pathlib import Path
from typing import Any

from ebrl import config as config_mod, graph

KINDS = ("uniform", "log_uniform", "int", "log_int", "choice")
REDUCE = ("last", "best", "mean_last")
SERVICES = tuple(name for name, role in graph.ROLES.items() if role.stats)  # the roles that report stats
TOP_KEYS = ("config", "study", "n_trials", "jobs", "cores_per_trial", "storage", "directory", "max_failures",
            "set", "params", "objective", "budget", "sampler", "pruner")
OBJECTIVE_KEYS = ("metric", "direction", "reduce", "last_n", "service")
BUDGET_KEYS = ("iterations", "seconds", "env_steps")
OWN_KEYS = ("run.name", "run.output_dir")  # the sweep sets these for each trial
CORES_PER_TRIAL = 2  # a quickstart-sized run (8 envs, gen, train) learns at full speed on 2 cores


class SweepError(ValueError):
    """A sweep that cannot run; the message names the key, the param or the flag."""


@dataclasses.dataclass(frozen=True)
class Param:
    """One swept config key and its distribution: ``uniform``/``log_uniform`` floats in [low, high] (with an
    optional ``step``), ``int``/``log_int`` integers, or a ``choice`` among values of any TOML type."""

    key: str
    kind: str
    low: float | int | None = None
    high: float | int | None = None
    step: float | int | None = None
    choices: tuple[Any, ...] = ()

    def suggest(self, trial: Any) -> Any:
        """This param's value for an Optuna trial (``trial.suggest_*`` under the config key's name)."""
        if self.kind in ("uniform", "log_uniform"):
            return trial.suggest_float(self.key, self.low, self.high, log=self.kind == "log_uniform", step=self.step)
        if self.kind in ("int", "log_int"):
            return trial.suggest_int(self.key, int(self.low), int(self.high), step=int(self.step or 1),
                                     log=self.kind == "log_int")
        return self.value_of(trial.suggest_categorical(self.key, self.labels))

    @property
    def labels(self) -> tuple[Any, ...]:
        """The choices as Optuna stores them: scalars as they are; lists and tables as JSON text (Optuna's
        categorical values are scalars)."""
        if all(isinstance(c, (bool, int, float, str)) for c in self.choices):
            return self.choices
        return tuple(json.dumps(c) for c in self.choices)

    def value_of(self, stored: Any) -> Any:
        """The config value of what Optuna stored for this param (a trial's ``params[key]``)."""
        if self.kind == "choice" and self.labels != self.choices:
            return json.loads(stored)
        return stored

    def edges(self) -> list[Any]:
        """The values :func:`check` tries: both ends of the range (as the type a trial gets: a float range's ends
        as floats), or every choice."""
        if self.kind == "choice":
            return list(self.choices)
        cast = int if self.kind in ("int", "log_int") else float
        return [cast(self.low), cast(self.high)]

    def override(self, value: Any) -> str:
        """``key=value`` as ``ebrl up --set`` takes it."""
        return config_mod.override(self.key, value)

    def describe(self) -> str:
        if self.kind == "choice":
            return f"choice of {', '.join(json.dumps(c) for c in self.choices)}"
        return f"{self.kind} [{self.low:g}, {self.high:g}]" + (f" step {self.step:g}" if self.step else "")


@dataclasses.dataclass(frozen=True)
class Objective:
    """The number a trial is judged by: ``metric`` of the run's stats (from the service its prefix names, else any
    that publishes it), each training update a point of its curve, reduced to one value: ``last`` (at the run's
    end), ``best`` (the best point) or ``mean_last`` (the mean of the last ``last_n`` points)."""

    metric: str = "train/episode_return_mean"
    direction: str = "maximize"
    reduce: str = "last"
    last_n: int = 5
    service: str | None = None

    @property
    def source(self) -> str | None:
        """The service whose reports carry the metric (None: any)."""
        prefix = self.metric.partition("/")[0]
        return self.service or (prefix if prefix in SERVICES else None)

    def describe(self) -> str:
        how = {"last": "at the run's end", "best": "its best point",
               "mean_last": f"mean of the last {self.last_n} points"}[self.reduce]
        return f"{self.direction} {self.metric} ({how})"


@dataclasses.dataclass(frozen=True)
class Budget:
    """How long each trial runs: ``iterations`` (its run.iterations), and the sweep stops it earlier after
    ``seconds`` (from its start) or once training took ``env_steps``; none: the config's own run.iterations."""

    iterations: int | None = None
    seconds: float | None = None
    env_steps: int | None = None

    def overrides(self) -> list[str]:
        return [config_mod.override("run.iterations", self.iterations)] if self.iterations else []


@dataclasses.dataclass
class Sweep:
    """A sweep, read and resolved (:func:`load`)."""

    config: str
    study: str
    directory: Path
    storage: str
    n_trials: int
    jobs: int
    cores_per_trial: int
    params: list[Param]
    fixed: list[str]
    objective: Objective
    budget: Budget
    sampler: dict[str, Any]
    pruner: dict[str, Any]
    max_failures: int = 3
    source: Path | None = None

    def overrides(self) -> list[str]:
        """What every trial's ``ebrl up`` gets before its params: the fixed ``[set]`` and the budget."""
        return [*self.fixed, *self.budget.overrides()]

    def trial_overrides(self, name: str, values: dict[str, Any]) -> list[str]:
        """A trial's ``--set`` items: the sweep's, its params' values, its run name and directory."""
        own = [config_mod.override("run.name", name),
               config_mod.override("run.output_dir", str((self.directory / "trials").resolve()))]
        return [*self.overrides(), *(p.override(values[p.key]) for p in self.params if p.key in values), *own]

    def param(self, key: str) -> Param | None:
        return next((p for p in self.params if p.key == key), None)


def load(target: str, *, params: list[str] = (), sets: list[str] = (), **given: Any) -> Sweep:
    """``target``: a sweep file, or a config (a path or a stock config's name) swept by the flags alone.
    ``params``: ``--param KEY=DIST`` items; ``sets``: ``--set KEY=VALUE`` items (after the file's ``[set]``);
    ``given``: the flags that replace the file's values (None: not given): ``n_trials``, ``jobs``, ``storage``,
    ``study``, ``directory``, ``metric``, ``direction``, ``iterations``."""
    raw, source = read(target)
    for item in params:
        key, spec = parse_param_flag(item)
        raw["params"][key] = spec
    raw["set"] += list(sets)
    for key, value in given.items():
        if value is None:
            continue
        if key in ("metric", "direction"):
            raw.setdefault("objective", {})[key] = value
        elif key == "iterations":
            raw.setdefault("budget", {})[key] = value
        else:
            raw[key] = value
    return from_raw(raw, source, default_study=Path(target).stem)


def read(target: str) -> tuple[dict[str, Any], Path | None]:
    """The raw tables of a sweep file (its ``params`` and ``set`` flattened to config keys, its ``config``
    resolved from the file's directory), or of a sweep of config ``target`` with nothing else yet."""
    path = Path(target)
    raw: dict[str, Any] = {}
    if path.is_file():
        try:
            raw = tomllib.loads(path.read_text())
        except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
            raise SweepError(f"{path}: not valid TOML: {exc}") from None
    if "config" not in raw and (sweepish := [key for key in ("params", "objective", "budget", "n_trials", "study")
                                             if key in raw]):
        raise SweepError(f"{path}: a sweep file ({', '.join(sweepish)}) needs `config = ...`: the config every trial "
                         "runs (a path or a stock config's name)")
    if "config" not in raw:  # a run config (or a stock config's name): the flags give the sweep
        try:
            config_mod.find(target)
        except config_mod.ConfigError as exc:
            raise SweepError(f"{target}: neither a sweep file (a TOML file with a top-level `config`) nor a config: "
                             f"{exc}") from None
        return {"config": target, "params": {}, "set": []}, None
    _known(raw, TOP_KEYS, "", path)
    if not isinstance(raw["config"], str) or not raw["config"]:
        raise SweepError(f"{path}: config = {raw['config']!r}: a config's path or a stock config's name")
    beside = path.parent / raw["config"]
    raw["config"] = str(beside.resolve()) if beside.is_file() else raw["config"]
    raw["params"] = dict(flatten_params(_table(raw, "params", path)))
    raw["set"] = [config_mod.override(key, value) for key, value in flatten_set(_table(raw, "set", path))]
    return raw, path.resolve()


def from_raw(raw: dict[str, Any], source: Path | None, default_study: str) -> Sweep:
    """A :class:`Sweep` from :func:`read`'s tables (with the flags applied); SweepError naming what is wrong."""
    where = source or "sweep"
    for section, keys in (("objective", OBJECTIVE_KEYS), ("budget", BUDGET_KEYS)):
        _known(_table(raw, section, where), keys, f"{section}.", where)
    study = str(raw.get("study") or default_study)
    directory = Path(raw.get("directory") or Path("sweeps") / slug(study))
    storage = raw.get("storage") or f"sqlite:///{(directory / 'study.db').resolve()}"
    n_trials = _int(raw, "n_trials", 20, 1, where)
    params = [parse_param(key, spec) for key, spec in raw["params"].items()]
    if not params:
        raise SweepError(f"{where}: no params to sweep: a [params] table (train.lr = {{log_uniform = [1e-4, 3e-3]}}) "
                         "or --param KEY=DIST")
    touched = [p.key for p in params] + [item.partition("=")[0].strip() for item in raw["set"]]
    if own := [key for key in touched if key in OWN_KEYS]:
        raise SweepError(f"{where}: {', '.join(own)}: the sweep names each trial's run and puts it in the sweep's "
                         "directory (set `directory` instead)")
    objective = _objective(_table(raw, "objective", where), where)
    budget = _budget(_table(raw, "budget", where), where)
    sampler = _named(raw, "sampler", "tpe", where)
    pruner = _named(raw, "pruner", "median", where)
    return Sweep(config=raw["config"], study=study, directory=directory, storage=str(storage), n_trials=n_trials,
                 jobs=_int(raw, "jobs", 0, 0, where), cores_per_trial=_int(raw, "cores_per_trial", CORES_PER_TRIAL, 1,
                                                                         where),
                 params=params, fixed=list(raw["set"]), objective=objective, budget=budget, sampler=sampler,
                 pruner=pruner, max_failures=_int(raw, "max_failures", 3, 1, where), source=source)


def check(sweep: Sweep) -> config_mod.Config:
    """The config every trial starts from (the sweep's ``[set]`` and budget applied), after loading it with each
    param at each end of its range (each choice): a key that is not a config key, or a value the config refuses,
    is a SweepError naming the param (the config's own message says why)."""
    try:
        base = config_mod.load(sweep.config, sweep.overrides())
    except config_mod.ConfigError as exc:
        raise SweepError(f"config {sweep.config} with the sweep's [set] and budget: {exc}") from None
    for param in sweep.params:
        for value in param.edges():
            try:
                config_mod.load(sweep.config, [*sweep.overrides(), param.override(value)])
            except config_mod.ConfigError as exc:
                raise SweepError(f"params.{param.key} = {json.dumps(value)}: {exc}") from None
    if base.run.iterations == 0 and not (sweep.budget.seconds or sweep.budget.env_steps):
        raise SweepError(f"config {sweep.config}: run.iterations = 0 runs until Ctrl-C; give each trial a budget "
                         "([budget] iterations, seconds or env_steps)")
    return base


def parse_param(key: str, spec: Any) -> Param:
    """One ``[params]`` entry: ``{log_uniform = [1e-4, 3e-3]}``, ``{int = [4, 16], step = 4}``,
    ``{choice = [[64, 64], [128, 128]]}``; a SweepError naming the param where it is not one."""
    where = f"params.{key}"
    example = "e.g. {log_uniform = [1e-4, 3e-3]}, {int = [4, 16]} or {choice = [true, false]}"
    if len(split_key(key)) < 2:
        raise SweepError(f"{where}: a config key is section.key (e.g. train.lr)")
    if not isinstance(spec, dict):
        raise SweepError(f"{where} = {spec!r}: a distribution, {example}")
    kinds = [k for k in spec if k in KINDS]
    other = [k for k in spec if k not in (*KINDS, "step")]
    if len(kinds) != 1 or other:
        wrong = other[0] if other else ", ".join(kinds) or "none"
        close = difflib.get_close_matches(other[0], KINDS, 1) if other else []
        hint = f" (did you mean {close[0]}?)" if close else ""
        raise SweepError(f"{where}: distribution {wrong}{hint}: give one of {', '.join(KINDS)}, {example}")
    kind = kinds[0]
    args, step = spec[kind], spec.get("step")
    if kind == "choice":
        if not isinstance(args, list) or not args or step is not None:
            raise SweepError(f"{where}: choice = {args!r}: a non-empty list of values (no step)")
        return Param(key, kind, choices=tuple(args))
    return _range(key, kind, args, step)


def _range(key: str, kind: str, args: Any, step: Any) -> Param:
    where = f"params.{key}: {kind} = {args!r}"
    number = int if kind in ("int", "log_int") else (int, float)
    if (not isinstance(args, list) or len(args) != 2
            or not all(isinstance(a, number) and not isinstance(a, bool) for a in args)):
        whole = "integers" if number is int else "numbers"
        raise SweepError(f"{where}: [low, high], two {whole}")
    low, high = args
    if not low < high:
        raise SweepError(f"{where}: low must be below high")
    if kind.startswith("log") and low <= 0:
        raise SweepError(f"{where}: a log scale needs low > 0")
    if step is not None:
        if kind.startswith("log"):
            raise SweepError(f"params.{key}: step with {kind}: a log scale has no step (use {kind.removeprefix('log_')})")
        if not isinstance(step, number) or isinstance(step, bool) or not step > 0:
            raise SweepError(f"params.{key}: step = {step!r}: a number > 0" + (" (an integer)" if number is int else ""))
    return Param(key, kind, low, high, step)


def parse_param_flag(item: str) -> tuple[str, dict[str, Any]]:
    """``--param KEY=DIST``: DIST as a TOML inline table (``train.lr={log_uniform=[1e-4,3e-3]}``) or short,
    ``KIND:ARGS`` (``train.lr=log_uniform:1e-4,3e-3``, ``algo.epochs=int:4,16,4``: with a step,
    ``policy.hidden=choice:[64,64],[128,128]``)."""
    key, eq, text = item.partition("=")
    key, text = key.strip(), text.strip()
    if not eq or not key or not text:
        raise SweepError(f"--param {item!r}: expected KEY=DIST, e.g. train.lr=log_uniform:1e-4,3e-3")
    if text.startswith("{"):
        try:
            return key, tomllib.loads(f"v = {text}")["v"]
        except tomllib.TOMLDecodeError as exc:
            raise SweepError(f"--param {item!r}: not a TOML inline table: {exc}") from None
    kind, colon, args = text.partition(":")
    if not colon:
        raise SweepError(f"--param {item!r}: expected KIND:ARGS (e.g. log_uniform:1e-4,3e-3) or a TOML table")
    try:
        values = tomllib.loads(f"v = [{args}]")["v"]
    except tomllib.TOMLDecodeError:  # bare words: choice:ebrl,async
        values = [a.strip() for a in args.split(",")]
    if kind.strip() == "choice" or len(values) != 3:
        return key, {kind.strip(): values}
    return key, {kind.strip(): values[:2], "step": values[2]}


def flatten_params(table: dict[str, Any], prefix: str = "") -> list[tuple[str, Any]]:
    """``[params]`` as (config key, distribution): a table naming a distribution kind (or, below a section, one
    that holds anything but tables: a misspelt kind) is a distribution; other tables are sections and sub-tables
    (``train.lr = {...}`` written as a dotted key makes ``train = {lr = {...}}``)."""
    out = []
    for name, value in table.items():
        key = join_key(prefix, name)
        section = not prefix and "." not in name
        if isinstance(value, dict) and value and not any(k in KINDS for k in value) \
                and (section or all(isinstance(v, dict) for v in value.values())):
            out += flatten_params(value, key)
        else:
            out.append((key, value))
    return out


def flatten_set(table: dict[str, Any], prefix: str = "") -> list[tuple[str, Any]]:
    """``[set]`` as (config key, value): its tables are sections and sub-tables (``env.kwargs.obs``)."""
    out = []
    for name, value in table.items():
        key = join_key(prefix, name)
        out += flatten_set(value, key) if isinstance(value, dict) and value else [(key, value)]
    return out


def join_key(prefix: str, name: str) -> str:
    """A TOML dotted key: ``name`` quoted where it is not a bare key (``env.kwargs."a.b"``). At the top, where
    only sections are (no section has a dot), a quoted ``"algo.clip"`` is the dotted key ``algo.clip``."""
    bare = r"[A-Za-z0-9_-]+(\.[A-Za-z0-9_-]+)*" if not prefix else r"[A-Za-z0-9_-]+"
    part = name if re.fullmatch(bare, name) else json.dumps(name)
    return f"{prefix}.{part}" if prefix else part


def split_key(key: str) -> list[str]:
    try:
        parsed = tomllib.loads(f"{key} = 0")
    except tomllib.TOMLDecodeError:
        return [key]
    path = []
    while isinstance(parsed, dict) and len(parsed) == 1:
        name, parsed = next(iter(parsed.items()))
        path.append(name)
    return path


def slug(text: str) -> str:
    """``text`` as a run name's part and a directory name: lowercase letters, digits, ``_ . -``."""
    return re.sub(r"[^a-z0-9_.-]+", "-", text.lower()).strip("-.") or "sweep"


def default_jobs(cores_per_trial: int, cores: int | None = None) -> int:
    """Trials at once on this host: one per ``cores_per_trial`` of the cores this process may use."""
    cores = len(os.sched_getaffinity(0)) if cores is None else cores
    return max(1, cores // cores_per_trial)


def core_slots(jobs: int, cores_per_trial: int, cores: list[int] | None = None) -> list[list[int] | None]:
    """The cores each of ``jobs`` trial slots is pinned to: disjoint sets of ``cores_per_trial`` where they fit on
    this host's cores, else None for every slot (each trial may use every core)."""
    cores = sorted(os.sched_getaffinity(0)) if cores is None else sorted(cores)
    if jobs * cores_per_trial > len(cores) or jobs == 1:
        return [None] * jobs
    return [cores[i * cores_per_trial:(i + 1) * cores_per_trial] for i in range(jobs)]


def _objective(table: dict[str, Any], where: Any) -> Objective:
    objective = Objective(**table)
    if not isinstance(objective.metric, str) or "/" not in objective.metric:
        raise SweepError(f"{where}: objective.metric = {objective.metric!r}: a metric of the run's stats, e.g. "
                         "train/episode_return_mean (docs/stats.md lists them)")
    if objective.direction not in ("maximize", "minimize"):
        raise SweepError(f"{where}: objective.direction = {objective.direction!r}: maximize or minimize")
    if objective.reduce not in REDUCE:
        raise SweepError(f"{where}: objective.reduce = {objective.reduce!r}: one of {', '.join(REDUCE)}")
    if not isinstance(objective.last_n, int) or objective.last_n < 1:
        raise SweepError(f"{where}: objective.last_n = {objective.last_n!r}: an integer >= 1")
    if objective.service is not None and objective.service not in SERVICES:
        raise SweepError(f"{where}: objective.service = {objective.service!r}: one of {', '.join(SERVICES)}")
    return objective


def _budget(table: dict[str, Any], where: Any) -> Budget:
    for key, value in table.items():
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not value > 0 \
                or (key != "seconds" and not isinstance(value, int)):
            raise SweepError(f"{where}: budget.{key} = {value!r}: a number > 0" + ("" if key == "seconds" else
                                                                                  " (an integer)"))
    return Budget(**table)


def _named(raw: dict[str, Any], section: str, default: str, where: Any) -> dict[str, Any]:
    """``sampler = "random"`` or a ``[sampler]`` table with ``name`` and the constructor's own arguments."""
    value = raw.get(section, {})
    table = {"name": value} if isinstance(value, str) else dict(_table(raw, section, where))
    table.setdefault("name", default)
    return table


def _table(raw: dict[str, Any], name: str, where: Any) -> dict[str, Any]:
    value = raw.get(name, {})
    if not isinstance(value, dict):
        raise SweepError(f"{where}: {name} = {value!r}: a table ([{name}])")
    return value


def _int(raw: dict[str, Any], key: str, default: int, least: int, where: Any) -> int:
    value = raw.get(key, default)
    if isinstance(value, bool) or not isinstance(value, int) or value < least:
        raise SweepError(f"{where}: {key} = {value!r}: an integer >= {least}")
    return value


def _known(table: dict[str, Any], allowed: tuple[str, ...], prefix: str, where: Any) -> None:
    for key in table:
        if key not in allowed:
            close = difflib.get_close_matches(key, allowed, 1)
            hint = f" (did you mean {prefix}{close[0]}?)" if close else ""
            raise SweepError(f"{where}: unknown key {prefix}{key}{hint}; known: {', '.join(allowed)}")
