"""A new service is three files: its module, its record in ebrl/graph.py and its tests (docs/contributing.md, "A
new service"). Here a copy of the package gets the first two, an ``audit`` service that reads every stats report of
its run and reports how many as a metric of its own, and nothing else is edited: what the rest of EBRL derives from
the graph must then know it (start order, the launcher's module, the plan, the sign-in identities and their
rights, the metric catalog and its page's section), and a real ``ebrl up`` of the copy starts it, lets it read and
publish, and its metric arrives."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from ebrl.testing import Run, StatsWatcher
from helpers import ROOT

RECORD = '''\
    Role("audit", start=8, stats="audit", about="A new service's own metrics: the stats reports it read.",
         optional=True, with_train=True,
         metrics=(Metric("audit/reports", "reports", "stats reports read", "services/audit.py", counter=True),),
         flows=(Flow("stats", "sub", (keys.stats_all, R), EVERY_STAT, "every report, to audit"),)),
'''

MODULE = '''\
"""audit service: counts the stats reports of its run."""

from __future__ import annotations

import asyncio

from ebrl.messages import decode_stats_sample
from ebrl.service import Service, service_main


class AuditService(Service):
    role = "audit"

    async def setup(self) -> None:
        self.inbox = self.bus.subscribe(self.keys.sub("stats"), decode_stats_sample, policy="latest", capacity=1000)

    async def run(self) -> None:
        while True:
            await asyncio.sleep(0.2)
            self.count("audit/reports", len(self.inbox.drain()))


def main() -> None:
    service_main(AuditService)


if __name__ == "__main__":
    main()
'''

FACTS = '''\
import json
import ebrl
from ebrl import config, graph, hosts, launch, metrics
from ebrl.config import from_dict

cfg = from_dict({})
acl = graph.access_control("r")
rules = [r for r in acl["rules"] if any("ebrl/stats/r/audit" in k for k in r.get("key_exprs", ()))]
print(json.dumps({
    "package": ebrl.__file__,
    "roles": config.ROLES,
    "module": graph.ROLES["audit"].module,
    "enabled": hosts.enabled_roles(cfg),
    "with_train": hosts.plan(cfg, only="train")[1].roles,
    "optional": "audit" in launch.OPTIONAL_ROLES,
    "metric": getattr(metrics.describe("audit/reports_per_s"), "name", None),
    "section": metrics.SECTIONS.get("audit"),
    "identity": graph.username("audit") in json.dumps(acl),
    "publishes_stats": bool(rules),
    "charted": "audit" in graph.markdown(),
}))
'''


def with_audit(tmp_path: Path) -> Path:
    """A copy of the checkout's package with the audit service's two files: its record in the graph, its module."""
    root = tmp_path / "fork"
    shutil.copytree(ROOT / "ebrl", root / "ebrl", ignore=shutil.ignore_patterns("__pycache__"))
    graph = root / "ebrl" / "graph.py"
    text = graph.read_text()
    anchor = '    Role("launcher", stats="launcher"'
    assert text.count(anchor) == 1
    graph.write_text(text.replace(anchor, RECORD + anchor))
    (root / "ebrl" / "services" / "audit.py").write_text(MODULE)
    return root


def in_fork(root: Path) -> dict[str, str]:
    return {**os.environ, "PYTHONPATH": str(root)}


def test_what_ebrl_derives_from_the_graph_knows_a_new_service(tmp_path):
    root = with_audit(tmp_path)
    out = subprocess.run([sys.executable, "-c", FACTS], cwd=root, env=in_fork(root), capture_output=True,
                         text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    facts = json.loads(out.stdout)
    assert Path(facts["package"]).is_relative_to(root)
    assert facts["roles"][-1] == "audit" and facts["module"] == "ebrl.services.audit"
    assert "audit" in facts["enabled"] and "audit" in facts["with_train"] and facts["optional"]
    assert facts["metric"] == "audit/reports" and facts["section"].startswith("A new service's")
    assert facts["identity"] and facts["publishes_stats"] and facts["charted"]


def test_a_role_declaring_a_metric_outside_its_namespace_is_refused(tmp_path):
    root = with_audit(tmp_path)
    graph = root / "ebrl" / "graph.py"
    graph.write_text(graph.read_text().replace('Metric("audit/reports"', 'Metric("sim/audit_reports"'))
    out = subprocess.run([sys.executable, "-c", "import ebrl.metrics"], cwd=root, env=in_fork(root),
                         capture_output=True, text=True, timeout=60)
    assert out.returncode != 0 and "outside its namespace audit/: sim/audit_reports" in out.stderr


@pytest.mark.slow
def test_ebrl_up_runs_a_new_service_from_its_module_and_record(tmp_path):
    root = with_audit(tmp_path)
    with Run(root / "ebrl" / "configs" / "quickstart.toml", "run.iterations=3", name="audit",
             out_dir=tmp_path / "runs", cwd=root, package=root) as run, StatsWatcher(run) as stats:
        code = run.wait(240)
        reports = stats.by_source()
    assert code == 0, run.output
    audit = reports.get("audit/0", [])
    assert audit and max(m.get("audit/reports", 0) for m in audit) > 0, sorted(reports)
