"""The import graph of ``ebrl/`` has no cycle and never runs up the layers; no module, class or function is
past its size.

The graph is read from the source (the AST of every module under ebrl/), not by importing anything, and
holds only what runs when a module is imported:

* Module-level imports only. An import inside a function (a lazy import, e.g. ``ebrl.bus.__getattr__``)
  or under ``if TYPE_CHECKING:`` / ``if __name__ == "__main__":`` runs later or never, so it is no edge.
  Imports in class bodies, ``try`` blocks and other module-level statements are edges.
* ``import ebrl.a.b`` and ``from ebrl.a import b`` where ``ebrl/a/b`` is a module depend on ``ebrl.a.b``;
  ``from ebrl.a import name`` where ``name`` is not a module depends on ``ebrl.a`` (its ``__init__``, or
  ``a.py``), which must have defined ``name`` by then.
* Importing ``ebrl.a.b`` first runs the ``__init__`` of each package on the way (``ebrl``, ``ebrl.a``), so
  the importer depends on those too, except on the packages that contain the importer itself: those
  ``__init__`` have already started before any module inside them runs, so the import needs nothing more
  of them. This is what makes the normal case acyclic: ``ebrl/a/__init__.py`` importing ``ebrl.a.b``, and
  ``ebrl/a/b.py`` importing its sibling ``ebrl.a.c``, add no edge back to ``ebrl.a``. A module that asks its
  own package for a name (``from ebrl.a import name`` inside ``ebrl/a/b.py``) does depend on ``ebrl.a``'s
  ``__init__``, and is a cycle when that ``__init__`` imports it (the name is not defined yet).

A toy package checks the model against Python itself: the one cycle it finds is an import that fails.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PACKAGE = "ebrl"

Edge = tuple[str, str]


def modules(root: Path = ROOT, package: str = PACKAGE) -> dict[str, Path]:
    """Every module of ``package`` under ``root``, by dotted name (a package by its own name: its __init__.py)."""
    found = {}
    for path in sorted((root / package).rglob("*.py")):
        parts = path.relative_to(root).with_suffix("").parts
        found[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return found


def module_level_imports(tree: ast.Module, lazy: bool = False) -> list[ast.Import | ast.ImportFrom]:
    """The import statements that run when the module is imported (see the module docstring); with ``lazy``,
    the ones inside functions too (an import that waits for a call is still a dependency)."""
    found: list[ast.Import | ast.ImportFrom] = []

    def visit(statements: list[ast.stmt]) -> None:
        for node in statements:
            if isinstance(node, (ast.Import, ast.ImportFrom)):
                found.append(node)
            elif isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                if lazy:
                    visit(node.body)
                continue
            elif isinstance(node, ast.If) and (_type_checking(node.test) or _main_guard(node.test)):
                visit(node.orelse)
            else:  # class bodies, try/except/finally, with, for, while, if/else, match: all run on import
                for child in ast.iter_child_nodes(node):
                    if isinstance(child, ast.stmt):
                        visit([child])
                    elif isinstance(child, (ast.excepthandler, ast.match_case)):
                        visit(child.body)

    visit(tree.body)
    return found


def _type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


def _main_guard(test: ast.expr) -> bool:
    return (isinstance(test, ast.Compare) and isinstance(test.left, ast.Name) and test.left.id == "__name__"
            and any(isinstance(c, ast.Constant) and c.value == "__main__" for c in test.comparators))


def import_graph(root: Path = ROOT, package: str = PACKAGE, lazy: bool = False) -> dict[Edge, str]:
    """Edges importer -> imported module within ``package``, each with where it comes from (``path:line``);
    ``lazy``: imports inside functions count too."""
    known = modules(root, package)
    packages = {name for name, path in known.items() if path.name == "__init__.py"}
    edges: dict[Edge, str] = {}
    for importer, path in known.items():
        own_package = importer if importer in packages else importer.rpartition(".")[0]
        containing = {".".join(importer.split(".")[:i]) for i in range(1, importer.count(".") + 1)}
        for node in module_level_imports(ast.parse(path.read_text(), str(path)), lazy):
            if isinstance(node, ast.Import):
                targets = [alias.name for alias in node.names]
            else:
                base = node.module or ""
                if node.level:  # relative: from the importer's package, up level - 1
                    anchor = own_package.split(".")[:len(own_package.split(".")) - (node.level - 1)]
                    base = ".".join(anchor + ([node.module] if node.module else []))
                targets = [f"{base}.{alias.name}" if f"{base}.{alias.name}" in known else base
                           for alias in node.names]
            for target in targets:
                if target not in known:  # another package, or no module of this one
                    continue
                parents = [".".join(target.split(".")[:i]) for i in range(1, target.count(".") + 1)]
                for dep in [p for p in parents if p not in containing and p != importer] + [target]:
                    if dep != importer:
                        edges.setdefault((importer, dep), f"{path.relative_to(root)}:{node.lineno}")
    return edges


def cycles(edges: dict[Edge, str]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan), each as a node list."""
    graph: dict[str, list[str]] = {}
    for a, b in edges:
        graph.setdefault(a, []).append(b)
        graph.setdefault(b, [])
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def connect(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                connect(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            connect(v)
    return found


def one_cycle(component: list[str], edges: dict[Edge, str]) -> str:
    """A shortest cycle through the component's first module, each import with where it is."""
    members, start = set(component), component[0]
    paths = {start: [start]}
    queue = [start]
    while queue:
        v = queue.pop(0)
        for a, b in sorted(edges):
            if a == v and b in members:
                if b == start:
                    hops = paths[v] + [start]
                    return "\n".join(f"  {x} -> {y}   ({edges[x, y]})" for x, y in zip(hops, hops[1:]))
                if b not in paths:
                    paths[b] = paths[v] + [b]
                    queue.append(b)
    raise AssertionError(f"no cycle through {start}")


TOY = {  # a package whose one cycle is real, next to the normal cases that are not cycles
    "toy/__init__.py": "",
    "toy/a/__init__.py": "from toy.a.x import X\n",  # a package's __init__ importing its submodule
    "toy/a/x.py": "from toy.a.y import Y\nfrom toy.a import y\nimport toy.b.z\nX = 1\n",  # siblings
    "toy/a/y.py": ("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from toy.a import X\n"
                   "def f():\n    from toy.a import X\nclass K:\n    import toy.b\nY = 1\n"),
    "toy/b/__init__.py": ("try:\n    import toy.b.w\nexcept ImportError:\n    pass\n"
                          "if __name__ == '__main__':\n    import toy.a\n"),
    "toy/b/w.py": "",
    "toy/b/z.py": "from toy.a import X\n",  # asks toy.a for a name toy.a is still importing: the cycle
}


def toy(root: Path, **replaced: str) -> Path:
    for name, text in {**TOY, **replaced}.items():
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        (root / name).write_text(text)
    return root


def imports_cleanly(root: Path, module: str) -> bool:
    code = f"import sys; sys.path.insert(0, {str(root)!r}); import {module}"
    return subprocess.run([sys.executable, "-c", code], capture_output=True, timeout=60).returncode == 0


def test_the_graph_has_an_edge_where_python_runs_an_import_and_finds_the_cycles_python_fails_on(tmp_path):
    edges = import_graph(toy(tmp_path / "cyclic"), "toy")
    assert set(edges) == {("toy.a", "toy.a.x"), ("toy.a.x", "toy.a.y"), ("toy.a.x", "toy.b"),
                          ("toy.a.x", "toy.b.z"), ("toy.a.y", "toy.b"), ("toy.b", "toy.b.w"), ("toy.b.z", "toy.a")}
    assert cycles(edges) == [["toy.a", "toy.a.x", "toy.b.z"]]
    assert "toy.b.z -> toy.a   (toy/b/z.py:1)" in one_cycle(cycles(edges)[0], edges)
    assert not imports_cleanly(tmp_path / "cyclic", "toy.a")  # Python agrees: "partially initialized module"
    fixed = toy(tmp_path / "fixed", **{"toy/b/z.py": "Z = 1\n"})
    assert cycles(import_graph(fixed, "toy")) == [] and imports_cleanly(fixed, "toy.a")


@pytest.mark.parametrize("lazy", [False, True], ids=["module-level", "inside-functions-too"])
def test_no_import_cycle_in_ebrl(lazy):
    """No cycle at all: an import inside a function that closes a cycle only hides it until the call (issue 37)."""
    edges = import_graph(lazy=lazy)
    found = cycles(edges)
    report = "\n\n".join(f"cycle among {', '.join(c)}:\n{one_cycle(c, edges)}" for c in found)
    assert not found, f"import cycles in ebrl/ ({'counting imports inside functions' if lazy else 'module-level'}):\n\n{report}"


# --- the layers (issue 55) --------------------------------------------------------------------------------

# The modules of ebrl in layers, lowest first. A module may import (at module level or inside a function) the
# modules of its own layer and of the layers below, never one of a layer above: the lower a module, the less it
# knows. A group names a module or a package; a package's group holds all of it but the modules named in a group
# of their own (the most specific name decides). The root package ``ebrl`` is its __init__ alone. The order is
# the one the imports have (docs/how-it-works.md, "Layers"); where two layers import nothing of each other, the
# lower is the one that should never learn of the other (the bus takes BusOptions, never the config).
LAYERS: list[tuple[str, tuple[str, ...]]] = [
    ("foundations: helpers, the wire formats, the service graph, the metric catalog",
     ("ebrl", "ebrl.durable", "ebrl.typecheck", "ebrl.devices", "ebrl.plugins", "ebrl.presets", "ebrl.procenv",
      "ebrl.meter", "ebrl.threads", "ebrl.metric", "ebrl.metrics", "ebrl.keys", "ebrl.codec", "ebrl.messages",
      "ebrl.graph")),
    ("the bus: Zenoh session, in-memory bus, sign-in, weights and stats over it",
     ("ebrl.bus", "ebrl.weights", "ebrl.stats")),
    ("hardware and simulators", ("ebrl.resources", "ebrl.envs", "ebrl.obswire")),
    ("policies", ("ebrl.policies",)),
    ("learning: algorithms, the learner, checkpoints", ("ebrl.algos",)),
    ("the config: checked against the registries below it (algorithms, policies, env backends)", ("ebrl.config",)),
    ("the logic the services and the launcher run",
     ("ebrl.sched", "ebrl.alloc", "ebrl.sizes", "ebrl.hosts", "ebrl.meta", "ebrl.tracking", "ebrl.viz",
      "ebrl.runview", "ebrl.evaluate", "ebrl.evaluate_suite", "ebrl.autotune", "ebrl.ranknet", "ebrl.slurm",
      "ebrl.policies.portable")),  # a policy file loaded on its own: it rebuilds the config it was trained with
    ("services, processes, the launcher",
     ("ebrl.service", "ebrl.services", "ebrl.process", "ebrl.launch", "ebrl.prepare", "ebrl.supervisor",
      "ebrl.stall", "ebrl.testing", "ebrl.bench", "ebrl.sweep")),
    ("entry points", ("ebrl.cli", "ebrl.api")),
]


def layer_of(module: str, layers: list[tuple[str, tuple[str, ...]]] = LAYERS, package: str = PACKAGE) -> int | None:
    """The index in ``layers`` of ``module``'s group (the most specific name that holds it); None: in none."""
    found, depth = None, -1
    for index, (_, groups) in enumerate(layers):
        for group in groups:
            holds = module == group or (group != package and module.startswith(group + "."))
            if holds and group.count(".") > depth:
                found, depth = index, group.count(".")
    return found


def arrows_up(edges: dict[Edge, str], layers: list[tuple[str, tuple[str, ...]]] = LAYERS,
              package: str = PACKAGE) -> list[str]:
    """Every import of ``edges`` from a module to one of a higher layer, with where it is."""
    up = []
    for (a, b), where in sorted(edges.items()):
        low, high = layer_of(a, layers, package), layer_of(b, layers, package)
        if low is not None and high is not None and low < high:
            up.append(f"  {a} ({layers[low][0].split(':')[0]}) -> {b} ({layers[high][0].split(':')[0]})   ({where})")
    return up


def test_the_layer_check_finds_an_import_up_also_inside_a_function(tmp_path):
    root = toy(tmp_path / "layered")
    layers = [("low", ("toy.a.y", "toy.b")), ("high", ("toy", "toy.a"))]
    assert layer_of("toy.a.x", layers, "toy") == 1 and layer_of("toy.a.y", layers, "toy") == 0
    assert layer_of("toy.b.w", layers, "toy") == 0 and layer_of("other", layers, "toy") is None
    assert arrows_up(import_graph(root, "toy"), layers, "toy") == [
        "  toy.b.z (low) -> toy.a (high)   (toy/b/z.py:1)"]
    # toy.a.y's ``def f(): from toy.a import X`` waits for a call, and is still an arrow up
    assert arrows_up(import_graph(root, "toy", lazy=True), layers, "toy") == [
        "  toy.a.y (low) -> toy.a (high)   (toy/a/y.py:5)", "  toy.b.z (low) -> toy.a (high)   (toy/b/z.py:1)"]


def test_every_module_of_ebrl_has_a_layer_and_every_group_a_module():
    names = modules()
    unplaced = sorted(name for name in names if layer_of(name) is None)
    assert not unplaced, f"modules in no layer (add each to its group in LAYERS): {unplaced}"
    groups = [group for _, layer in LAYERS for group in layer]
    stale = [group for group in groups if group not in names]
    assert not stale and len(groups) == len(set(groups)), f"LAYERS names no module, or twice: {stale or groups}"


def test_imports_never_run_up_the_layers():
    up = arrows_up(import_graph(lazy=True))
    assert not up, ("imports that run up the layers (counting imports inside functions; move the module to the "
                    "layer it belongs to, or pass in what it needs):\n" + "\n".join(up))


# --- the shape the services and the library keep (issue 16) ---------------------------------------------

# Limits on a principle (issue 37), not at the day's maximum: a service is an adapter (subscribe, call ebrl.*,
# publish) that reads on one screen or two; a class that grows past 200 lines holds two concepts; a function past
# 60 lines (a screen) does several things. Each is met with room to spare, so a change that needs more splits
# something instead of raising the limit.
SERVICE_LINES = 150
CLASS_LINES = 200
FUNCTION_LINES = 60
KEY_PREFIXES = ("ebrl/data", "ebrl/ctl", "ebrl/stats", "ebrl/live")


def test_services_are_thin_adapters():
    long = {p.name: n for p in sorted((ROOT / "ebrl" / "services").glob("*.py"))
            if (n := len(p.read_text().splitlines())) > SERVICE_LINES}
    assert not long, f"services over {SERVICE_LINES} lines (move their logic into ebrl/): {long}"


def test_no_class_in_ebrl_is_oversized():
    long = {}
    for name, path in modules().items():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ClassDef) and node.end_lineno - node.lineno + 1 > CLASS_LINES:
                long[f"{name}.{node.name}"] = node.end_lineno - node.lineno + 1
    assert not long, f"classes over {CLASS_LINES} lines: {long}"


# Files over FILE_LINES still to split, each with why it waits: the list only shrinks (a file split below the limit
# must leave it, the test says so).
FILE_LINES = 600
STILL_TO_SPLIT: dict[str, str] = {}  # none left (ebrl/config.py became the package ebrl/config/)


def test_no_file_in_ebrl_is_over_600_lines():
    """A module past 600 lines holds several concepts: split it along them (a package whose __init__ exports the
    names keeps its callers unchanged)."""
    lines = {str(path.relative_to(ROOT)): len(path.read_text().splitlines()) for path in modules().values()}
    long = {path: n for path, n in lines.items() if n > FILE_LINES and path not in STILL_TO_SPLIT}
    assert not long, f"files over {FILE_LINES} lines (split them along their concepts): {long}"
    done = [path for path in STILL_TO_SPLIT if lines.get(path, 0) <= FILE_LINES]
    assert not done, f"split already (or gone): take them off STILL_TO_SPLIT: {done}"


def test_no_function_is_over_a_screen():
    long = {}
    paths = modules()
    for name, path in paths.items():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                if (n := node.end_lineno - node.lineno + 1) > FUNCTION_LINES:
                    long[f"{name}.{node.name}"] = n
    assert not long, f"functions over {FUNCTION_LINES} lines (split them by what they do): {long}"


def test_keys_are_built_and_parsed_only_in_the_key_module():
    """No key f-strings (``f"ebrl/..."``) and no positional key parsing outside ebrl/keys.py."""
    offenders = []
    for path in sorted((ROOT / "ebrl").rglob("*.py")):
        if path == ROOT / "ebrl" / "keys.py":
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.JoinedStr) and node.values and isinstance(node.values[0], ast.Constant) \
                    and str(node.values[0].value).startswith(KEY_PREFIXES):
                offenders.append(f"{path.relative_to(ROOT)}:{node.lineno}: key f-string")
            if isinstance(node, ast.Subscript) and isinstance(node.value, ast.Call) \
                    and getattr(node.value.func, "attr", "") == "parse" \
                    and getattr(node.value.func.value, "id", "") == "keys":
                offenders.append(f"{path.relative_to(ROOT)}:{node.lineno}: keys.parse(...)[i]")
    assert not offenders, "\n".join(offenders)


def test_readme_headings_named_in_the_code_exist():
    """A message or comment that sends the user to a section of the documentation names one that is there:
    ``README: "Heading"`` a heading of README.md or of a page under docs/; ``docs/page.md`` a page that exists,
    and ``docs/page.md: "Heading"`` a heading of that page."""
    import re

    def headings(*pages: Path) -> list[str]:
        return [line.lstrip("#").strip() for page in pages for line in page.read_text().splitlines()
                if line.startswith("#")]

    everywhere = headings(ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md")))
    missing = []
    for path in sorted((ROOT / "ebrl").rglob("*.py")):
        text = path.read_text()
        for match in re.finditer(r'README: \\?"([^"\\]+)', text):
            if not any(h.startswith(match.group(1).strip()) for h in everywhere):
                missing.append(f"{path.relative_to(ROOT)}: {match.group(1)!r}")
        for match in re.finditer(r'\b(docs/[\w/.-]+\.md)(?:[:,] \\?"([^"\\]+))?', text):
            page = ROOT / match.group(1)
            if not page.is_file():
                missing.append(f"{path.relative_to(ROOT)}: {match.group(1)} (no such page)")
            elif match.group(2) and not any(h.startswith(match.group(2).strip()) for h in headings(page)):
                missing.append(f"{path.relative_to(ROOT)}: {match.group(1)}: {match.group(2)!r}")
    assert not missing, "README or docs/ headings that do not exist:\n" + "\n".join(missing)



# --- a simulator backend's facts in its record (issue 55) ---------------------------------------------------

# Where the backends' facts live: every other module asks a record (ebrl.envs.records.backend_record) instead of
# testing a backend's name, so that adding a backend touches its module, its record and its tests only.
BACKEND_RECORDS = ("ebrl/envs/records.py",)


def _names_in(node: ast.AST, names: tuple[str, ...]) -> bool:
    """Whether ``node`` is a backend name (a str literal) or a tuple, list or set literal holding one."""
    items = node.elts if isinstance(node, (ast.Tuple, ast.List, ast.Set)) else [node]
    return any(isinstance(item, ast.Constant) and item.value in names for item in items)


def _only_names(node: ast.AST, names: tuple[str, ...]) -> bool:
    """Whether ``node`` is a tuple, list or set literal of backend names only, or a dict literal keyed by them
    only: a table of backends (their facts kept outside their records)."""
    items = (node.elts if isinstance(node, (ast.Tuple, ast.List, ast.Set))
             else node.keys if isinstance(node, ast.Dict) else [])
    return bool(items) and all(isinstance(item, ast.Constant) and item.value in names for item in items)


def backend_name_tests(source: str, names: tuple[str, ...]) -> list[tuple[int, str]]:
    """Where ``source`` tests a backend's name: compared (``==``, ``!=``, ``in``, ``not in``, with a literal name or
    a literal collection holding one), looked up by a literal name (``table["mjwarp"]``, ``.get("mjwarp")``), a
    ``match`` case on one, or a table of backends (a collection of names only, a dict keyed by them)."""
    tree = ast.parse(source)
    compared = {id(side) for node in ast.walk(tree) if isinstance(node, ast.Compare)
                for side in (node.left, *node.comparators)}
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Compare) and any(_names_in(side, names) for side in (node.left, *node.comparators)):
            found.add((node.lineno, "compared"))
        elif isinstance(node, ast.Subscript) and _names_in(node.slice, names) and not isinstance(node.slice, ast.Tuple):
            found.add((node.lineno, "looked up by name"))
        elif isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "get" \
                and node.args and _names_in(node.args[0], names) and not isinstance(node.args[0], ast.Tuple):
            found.add((node.lineno, "looked up by name"))
        elif isinstance(node, ast.match_case) and any(isinstance(p, ast.MatchValue) and _names_in(p.value, names)
                                                      for p in ast.walk(node.pattern)):
            found.add((node.pattern.lineno, "a match case"))
        if _only_names(node, names) and id(node) not in compared:
            found.add((node.lineno, "a table of backends"))
    return sorted(found)


def backend_name_offenders(root: Path, package: str, names: tuple[str, ...],
                           records: tuple[str, ...] = BACKEND_RECORDS) -> list[str]:
    """Every backend name test in ``package`` under ``root`` outside ``records`` (paths relative to ``root``)."""
    out = []
    for path in sorted((root / package).rglob("*.py")):
        where = path.relative_to(root).as_posix()
        if where not in records:
            out += [f"{where}:{line}: {what}" for line, what in backend_name_tests(path.read_text(), names)]
    return out


TOY_NAME_TESTS = '''\
def vectorized(backend, kwargs):
    if backend == "mjwarp":
        return True
    if backend != "maniskill" and kwargs:
        return False
    return backend in ("gymnasium", "robosuite")
DEFAULT_OBS = {"libero": "rgb", "robosuite": "state"}
GPU_SIMULATORS = ("mjwarp",)
def obs(backend, table):
    return table["libero"], table.get("robosuite", "state"), DEFAULT_OBS.get(backend)
def rendered(backend):
    match backend:
        case "robosuite" | "libero":
            return True
    return backend not in ["mjwarp"]
'''
# what is no test of a name: a default, a message, an argument, a package list that names other packages too
TOY_CLEAN = '''\
import importlib.util
def spec(env, backend="gymnasium"):
    found = importlib.util.find_spec("robosuite")
    return env.get("backend", "gymnasium"), f"env.backend = 'libero' needs LIBERO", found
PACKAGES = ("ebrl", "torch", "gymnasium", "mujoco")
COMMANDS = {"libero": 1, "up": 2}
'''


def test_the_backend_name_check_finds_each_way_of_testing_a_name(tmp_path):
    names = ("gymnasium", "robosuite", "maniskill", "mjwarp", "libero")
    assert backend_name_tests(TOY_NAME_TESTS, names) == [
        (2, "compared"), (4, "compared"), (6, "compared"), (7, "a table of backends"), (8, "a table of backends"),
        (10, "looked up by name"), (13, "a match case"), (15, "compared")]
    assert backend_name_tests(TOY_CLEAN, names) == []
    root = toy(tmp_path / "named", **{"toy/a/sim.py": TOY_NAME_TESTS, "toy/b/records.py": TOY_NAME_TESTS,
                                      "toy/b/clean.py": TOY_CLEAN})
    found = backend_name_offenders(root, "toy", names, records=("toy/b/records.py",))
    assert len(found) == 8 and all(line.startswith("toy/a/sim.py:") for line in found)
    assert "toy/a/sim.py:13: a match case" in found


def test_no_backend_name_is_tested_outside_the_backend_records():
    """``env.backend``'s names (the registry's) are tested only in ebrl/envs/records.py."""
    from ebrl.envs.records import BACKENDS

    found = backend_name_offenders(ROOT, PACKAGE, tuple(BACKENDS))
    assert not found, ("backend names tested outside the backend records (ask the record instead: "
                       "ebrl.envs.records.backend_record(name)):\n" + "\n".join(found))


# --- keys from the service graph's builders (issue 55) ------------------------------------------------------------

KEY_PARSERS = ("parse", "role_of", "check_chunk")  # read a key or check a chunk: they build none


def key_builders(root: Path = ROOT) -> set[str]:
    """The key builders of ``ebrl/keys.py``: its module-level functions, less the parsers."""
    tree = ast.parse((root / "ebrl" / "keys.py").read_text())
    return {node.name for node in tree.body if isinstance(node, ast.FunctionDef)
            and not node.name.startswith("_") and node.name not in KEY_PARSERS}


def key_builder_calls(source: str, builders: set[str]) -> list[int]:
    """The lines of ``source`` that call a builder of ``ebrl.keys``: ``keys.obs(...)`` (``keys`` however imported
    or renamed), ``ebrl.keys.obs(...)``, or a builder imported by name (``from ebrl.keys import obs``)."""
    tree = ast.parse(source)
    modules, direct = set(), set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module == "ebrl":
            modules |= {a.asname or a.name for a in node.names if a.name == "keys"}
        elif isinstance(node, ast.ImportFrom) and node.module == "ebrl.keys":
            direct |= {a.asname or a.name for a in node.names if a.name in builders}
        elif isinstance(node, ast.Import):
            modules |= {a.asname for a in node.names if a.name == "ebrl.keys" and a.asname}
    found = []
    for node in ast.walk(tree):
        if not isinstance(node, ast.Call):
            continue
        func = node.func
        if isinstance(func, ast.Name) and func.id in direct:
            found.append(node.lineno)
        elif isinstance(func, ast.Attribute) and func.attr in builders and (
                isinstance(func.value, ast.Name) and func.value.id in modules
                or isinstance(func.value, ast.Attribute) and func.value.attr == "keys"
                and isinstance(func.value.value, ast.Name) and func.value.value.id == "ebrl"):
            found.append(node.lineno)
    return sorted(found)


def key_builder_offenders(root: Path, package: str, builders: set[str],
                          exempt: tuple[str, ...] = ("ebrl/keys.py", "ebrl/graph.py")) -> list[str]:
    """``path:line`` of every call of a key builder in ``package`` outside the ``exempt`` files."""
    return [f"{path.relative_to(root)}:{line}" for path in sorted((root / package).rglob("*.py"))
            if str(path.relative_to(root)) not in exempt
            for line in key_builder_calls(path.read_text(), builders)]


TOY_KEY_CALLS = '''\
from ebrl import keys
from ebrl import keys as k
from ebrl.keys import act
import ebrl.keys
keys.obs("r", 3)
k.stats("r", "sim", 0)
act("r")
ebrl.keys.live_all("r")
'''
TOY_KEY_CLEAN = '''\
from ebrl import graph, keys
keys.parse("ebrl/live/r/sim/0").service, keys.role_of("ebrl/live/r/sim/0"), keys.check_chunk("r", "run.name")
self.keys.put("obs", group=3), graph.keys_of("r", "sim").token()
keys = [1]; keys.append(2)
'''


def test_the_key_builder_check_finds_each_way_of_calling_one(tmp_path):
    builders = {"obs", "stats", "act", "live_all"}
    assert key_builder_calls(TOY_KEY_CALLS, builders) == [5, 6, 7, 8]
    assert key_builder_calls(TOY_KEY_CLEAN, builders) == []
    root = toy(tmp_path / "keyed", **{"toy/a/sim.py": TOY_KEY_CALLS, "toy/b/clean.py": TOY_KEY_CLEAN,
                                      "toy/graph.py": TOY_KEY_CALLS})
    found = key_builder_offenders(root, "toy", builders, exempt=("toy/graph.py",))
    assert found == ["toy/a/sim.py:5", "toy/a/sim.py:6", "toy/a/sim.py:7", "toy/a/sim.py:8"]
    assert {"obs", "stats", "live", "ctl", "weights_all"} <= key_builders() and not set(KEY_PARSERS) & key_builders()


def test_no_key_is_built_outside_the_graphs_builders():
    """Code gets its keys from ``ebrl.graph.keys_of(run, role, instance)`` (the keys of its role's declared flows);
    only ebrl/keys.py (the formats) and ebrl/graph.py (the graph's patterns) call the builders of ebrl.keys."""
    found = key_builder_offenders(ROOT, PACKAGE, key_builders())
    assert not found, ("keys built outside the service graph's builders (use ebrl.graph.keys_of(run, role, "
                       "instance).put/sub/...(flow)):\n" + "\n".join(found))
