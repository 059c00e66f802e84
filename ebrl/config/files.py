"""Config files: the stock configs, reading TOML (``base`` chains), ``--set`` overrides, building a
:class:`~ebrl.config.schema.Config` from a dict, writing it back, and ``ebrl config``'s description."""

from __future__ import annotations

import dataclasses
import difflib
import os
import tomllib
import types
import typing
from pathlib import Path
from typing import Any, Literal

import tomli_w

from ebrl import keys
from ebrl import typecheck
from ebrl.config.base import ConfigError
from ebrl.config.run import ROLES, HostEntry
from ebrl.config.schema import SECTIONS, Config, check_across


# Where the stock configs are: inside the package (a clone's configs/ links here).
STOCK_DIRS = (Path(__file__).resolve().parent.parent / "configs",)


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
            sections[name] = make_section(name, SECTIONS[name], value)
    cfg = Config(**sections)
    for name in SECTIONS:
        getattr(cfg, name).check()
    check_across(cfg)
    return cfg


def make_section(name: str, cls: type, values: dict[str, Any]) -> Any:
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
        entry = hosts[name] = make_section(f"hosts.{name}", HostEntry, value)
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
