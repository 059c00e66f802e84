"""The metric catalog (ebrl.metrics), from which docs/stats.md's table is generated, holds what the code publishes:
every record's name is in the source of the modules it names, every metric-like name the package's code writes or
reads is a record, and every metric real runs publish is one (:func:`assert_catalogued`, which the tests of those
runs call on the reports they collected: the quickstart in test_up, eval in test_eval_service, GRPO in
test_workloads, SAC in test_algorithms, every service in process in test_in_process, the allocator in
test_alloc_service; the slow test here runs the quickstart with the allocator, eval and viz at once)."""

from __future__ import annotations

import ast
import json
import re
from collections.abc import Iterable, Mapping
from pathlib import Path

import pytest

from ebrl import metrics
from ebrl.messages import StatsReport
from ebrl.metric import Metric
from ebrl.metrics import NAMESPACES

ROOT = Path(__file__).resolve().parent.parent
PACKAGE = ROOT / "ebrl"
# every namespace a metric name starts with
NAMESPACE = re.compile(r"^(%s)/" % "|".join((*NAMESPACES, "busy", "quota", "ctl", "bus", "proc", "slowdown", "cpu",
                                              "gpu")))
# literals with a metric's namespace that are no metric: a service instance (``sim/0``), cgroup v1 files
NOT_METRICS = re.compile(r"^\w+/\d+$|^cpu/cpu\.cfs_(quota|period)_us$")


# --- the runs' reports ---------------------------------------------------------------------------------------

def published(reports: Mapping[str, list[dict[str, float]]] | Iterable[StatsReport]) -> dict[str, set[str]]:
    """Every metric name in ``reports`` (``StatsWatcher.by_source()``'s ``{"<service>/<instance>": [metrics]}``, or
    StatsReports) with the services that published it."""
    names: dict[str, set[str]] = {}
    if isinstance(reports, Mapping):
        rows = [(source.split("/")[0], m) for source, ms in reports.items() for m in ms]
    else:
        rows = [(r.service, r.metrics) for r in reports]
    for service, values in rows:
        for name in values:
            names.setdefault(name, set()).add(service)
    return names


def uncatalogued(reports) -> list[str]:
    """What ``reports`` published that the catalog lacks, or says another service publishes, one line each."""
    out = []
    for name, services in sorted(published(reports).items()):
        record = metrics.describe(name)
        if record is None:
            out.append(f"{name} (from {', '.join(sorted(services))}): not in ebrl.metrics")
        elif not services <= set(record.services):
            out.append(f"{name} (from {', '.join(sorted(services))}): ebrl.metrics says {record.name} comes from "
                       f"{', '.join(record.services)}")
    return out


def assert_catalogued(reports) -> None:
    """Fail naming each metric of ``reports`` that ebrl.metrics (and so docs/stats.md) does not describe."""
    lines = uncatalogued(reports)
    assert not lines, ("metrics the run published that docs/stats.md lacks (declare them in ebrl/metrics/, then "
                       "python docs/gen.py):\n" + "\n".join(lines))


# --- the catalog against the source -----------------------------------------------------------------------------

def unsourced(metric: Metric, read=lambda module: (PACKAGE / module).read_text()) -> list[str]:
    """The modules of ``metric`` whose source does not name it: the whole name, or (a service's own namespace
    prepended elsewhere, ``f"train/{k}"``) the part after its namespace as a word; for a family each literal part
    between its placeholders."""
    out = []
    for module in metric.modules:
        text = read(module)
        first, *rest = metric.pieces
        tail = first.split("/", 1)[1]
        named = first in text or (tail and re.search(rf"(?<![\w]){re.escape(tail)}(?![a-z])", text))
        if not named or not all(piece in text for piece in rest):
            out.append(module)
    return out


def metric_literals() -> list[tuple[str, str]]:
    """(file:line, name) for every string with a metric's namespace in the package's code outside the catalog: a
    constant, or an f-string with ``<>`` where it has a value."""
    found = []
    for path in sorted(PACKAGE.rglob("*.py")):
        if path.parent.name == "metrics":
            continue
        tree = ast.parse(path.read_text())
        parts = {id(v) for node in ast.walk(tree) if isinstance(node, ast.JoinedStr) for v in node.values}
        for node in ast.walk(tree):
            if isinstance(node, ast.Constant) and isinstance(node.value, str) and id(node) not in parts:
                text = node.value
            elif isinstance(node, ast.JoinedStr):
                text = "".join(v.value if isinstance(v, ast.Constant) else "<>" for v in node.values)
            else:
                continue
            if NAMESPACE.match(text) and re.fullmatch(r"[\w.<>/-]+", text) and not NOT_METRICS.match(text):
                found.append((f"{path.relative_to(ROOT)}:{node.lineno}", text))
    return found


def covered(literal: str) -> bool:
    """Whether a name the code writes or reads is the catalog's: a metric, a family's member or its own f-string,
    a family's literal start or a namespace (prefixes the code filters by)."""
    if "<" not in literal:
        return metrics.describe(literal) is not None or any(
            (m.family and m.pieces[0] == literal) or (literal.endswith("/") and m.name.startswith(literal))
            for m in metrics.CATALOG)
    shape = re.compile(".+".join(re.escape(p) for p in literal.split("<>")))
    plain = re.compile(r"<[a-z]+>")
    return any(shape.fullmatch(name) or plain.sub("<>", name) == literal
               for m in metrics.CATALOG for name in m.names())


def test_every_record_is_named_in_the_modules_it_says_publish_it():
    stale = {m.name: unsourced(m) for m in metrics.CATALOG if unsourced(m)}
    assert not stale, f"records whose modules do not name them (renamed or gone?): {stale}"


def test_the_source_check_fails_a_record_the_code_does_not_have():
    assert unsourced(Metric("sim/env_stepz", "steps", "a typo", "sched/group.py")) == ["sched/group.py"]
    assert unsourced(Metric("sim/core<c>_idle_s", "s", "no such family", "services/sim.py")) == ["services/sim.py"]
    assert unsourced(Metric("train/policy_loss", "loss", "in another module", "algos/sac.py")) == ["algos/sac.py"]
    assert not unsourced(Metric("train/policy_loss", "loss", "PPO's update names it", "algos/ppo.py"))


def test_every_metric_name_in_the_code_is_in_the_catalog():
    unknown = [f"{where}: {name}" for where, name in metric_literals() if not covered(name)]
    assert not unknown, "metric names in ebrl/ that ebrl.metrics lacks:\n" + "\n".join(unknown)
    assert len(metric_literals()) > 300  # the scan sees the code: ~370 such literals


def test_describe_finds_counters_rates_and_families_and_nothing_else():
    assert metrics.describe("sim/env_steps").unit == "steps"
    assert metrics.describe("sim/env_steps_per_s") is metrics.describe("sim/env_steps")
    assert metrics.describe("sim/envs_per_s") is None  # a gauge has no rate
    assert metrics.describe("busy/sim.g3").name == "busy/<lane>"
    assert metrics.describe("sim/core1_busy_s_per_s").name == "sim/core<c>_busy_s"
    assert metrics.describe("alloc/cores_per_env").name == "alloc/cores_per_env"
    assert metrics.describe("alloc/cores_train").name == "alloc/cores_<stage>"
    assert metrics.describe("train/staleness_hist_12").services == ("train",)
    assert metrics.describe("train/vpg_loss") is None and metrics.describe("nothing") is None
    assert metrics.missing(["sim/env_steps", "sim/nope", "gen/obs_queue"]) == ["sim/nope"]


def test_a_run_that_publishes_a_metric_the_catalog_lacks_fails_naming_it():
    report = StatsReport(run="r", service="sim", instance=0, time=0.0, seq=0,
                         metrics={"sim/env_steps": 1.0, "sim/env_steps_per_s": 2.0, "sim/new_thing": 3.0,
                                  "train/updates": 1.0})
    assert uncatalogued([report]) == ["sim/new_thing (from sim): not in ebrl.metrics",
                                      "train/updates (from sim): ebrl.metrics says train/updates comes from train"]
    with pytest.raises(AssertionError, match="sim/new_thing"):
        assert_catalogued({"sim/0": [report.metrics]})


def test_the_catalog_is_data():
    import subprocess
    import sys

    code = "import sys, ebrl.metrics; print(sorted(m for m in ('torch', 'zenoh', 'numpy') if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, cwd=ROOT)
    assert out.stdout.strip() == "[]", out.stdout + out.stderr


# --- a real run of every optional service ----------------------------------------------------------------------

@pytest.mark.slow  # the fast suite checks the same runs' reports where it already runs them (the module docstring)
def test_every_metric_a_run_with_the_allocator_eval_and_viz_publishes_is_on_the_stats_page(tmp_path):
    import helpers
    from ebrl import autotune, config

    out_dir = tmp_path / "runs"
    overrides = ["alloc.enabled=true", "alloc.window=4", "alloc.patience=3", "run.iterations=4", "eval.every=2",
                 "eval.episodes=2", 'viz.rerun="save"', "sim.groups=2", "sim.envs_per_group=4"]
    cfg = config.load(str(helpers.ROOT / "configs/quickstart.toml"),
                      overrides + [f"run.output_dir={json.dumps(str(out_dir))}", "run.name=everything"])
    cfg, _ = autotune.settle(cfg, ("sim", "gen", "train", "alloc"), multi=False)
    helpers.store_profile(out_dir / "profiles" / "everything.json", cfg, gen_batches=(4, 8), train_batch=1024)
    code, out, seen = helpers.run_collecting_stats(out_dir, "configs/quickstart.toml", *overrides, run="everything")
    assert code == 0, out
    assert {"alloc", "eval", "viz", "log", "launcher"} <= {source.split("/")[0] for source in seen}
    assert_catalogued(seen)
