"""benchmarks/report.py: BENCHMARKS.md is up to date, and every number in it follows the JSON results."""

from __future__ import annotations

import importlib.util
import json
import shutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from types import ModuleType

import pytest
from jinja2.exceptions import SecurityError, UndefinedError
from jinja2.sandbox import SandboxedEnvironment

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "benchmarks" / "results"


def _load_report() -> ModuleType:
    spec = importlib.util.spec_from_file_location("benchmarks_report", ROOT / "benchmarks" / "report.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


report = _load_report()


@pytest.fixture
def results(tmp_path: Path) -> Path:
    """A copy of the recorded results (JSON files and the plots the report links to)."""
    out = tmp_path / "results"
    shutil.copytree(RESULTS, out, ignore=shutil.ignore_patterns("*.txt"))
    return out


def edit(path: Path, change: Callable[[dict], object]) -> None:
    data = json.loads(path.read_text())
    change(data)
    path.write_text(json.dumps(data))


def render(results: Path, tmp_path: Path, capsys) -> tuple[int, str, str]:
    out = tmp_path / "BENCHMARKS.md"
    rc = report.main(["--results", str(results), "--out", str(out)])
    captured = capsys.readouterr()
    return rc, out.read_text() if out.exists() else "", captured.err


def test_benchmarks_md_is_up_to_date():
    proc = subprocess.run([sys.executable, "benchmarks/report.py", "--check"], cwd=ROOT, capture_output=True,
                          text=True, timeout=60)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert (ROOT / "BENCHMARKS.md").read_text().startswith(report.HEADER)


def test_check_reports_a_stale_file_with_a_diff(tmp_path, capsys):
    out = tmp_path / "BENCHMARKS.md"
    out.write_text((ROOT / "BENCHMARKS.md").read_text().replace("env steps/s", "steps per second", 1))
    rc = report.main(["--out", str(out), "--check"])
    printed = capsys.readouterr().out
    assert rc == 1
    assert "+++ generated" in printed and "-" in printed and "steps per second" in printed


def test_a_missing_key_names_the_file_and_the_key(results, tmp_path, capsys):
    edit(results / "quickstart_learning.json", lambda d: d["summary"].pop("env_steps_per_s"))
    rc, _, err = render(results, tmp_path, capsys)
    assert rc == 2
    assert "quickstart_learning.json: missing key 'summary.env_steps_per_s'" in err
    assert "BENCHMARKS.template.md:" in err  # and the template line that reads it
    assert "Traceback" not in err

    edit(results / "quickstart_learning.json", lambda d: d["summary"].update(env_steps_per_s=None))
    rc, _, err = render(results, tmp_path, capsys)
    assert rc == 2 and "quickstart_learning.json: key 'summary.env_steps_per_s' is null" in err


def test_a_missing_key_in_a_list_names_its_index(results, tmp_path, capsys):
    edit(results / "allocator_quality.json", lambda d: d["cases"][2].pop("ratio_median"))
    rc, _, err = render(results, tmp_path, capsys)
    assert rc == 2 and "allocator_quality.json: missing key 'cases[2].ratio_median'" in err


def test_a_missing_key_in_a_modes_table_names_the_run(results, tmp_path, capsys):
    edit(results / "bench_w1_lift.json", lambda d: d["results"]["hybrid"][1].pop("idle_gen"))
    rc, _, err = render(results, tmp_path, capsys)
    assert rc == 2 and "bench_w1_lift.json" in err and "results.hybrid[1].idle_gen" in err


def test_a_missing_required_file_is_an_error_and_an_optional_one_drops_its_section(results, tmp_path, capsys):
    (results / "peer_sample_factory_async.json").unlink()  # optional section
    rc, text, err = render(results, tmp_path, capsys)
    assert rc == 0
    assert "async_rl=True" not in text and "`results/peer_sample_factory_async.json` is not recorded" in text
    assert "sample_factory_async" in err

    (results / "soak.json").unlink()  # required
    rc, _, err = render(results, tmp_path, capsys)
    assert rc == 2 and "soak.json: missing results file" in err


def test_numbers_follow_the_json(results, tmp_path, capsys):
    rc, before, _ = render(results, tmp_path, capsys)
    assert rc == 0 and "4,007 env steps/s" in before and "gen 297.3 → 297.6 MB" in before

    edit(results / "quickstart_learning.json", lambda d: d["summary"].update(env_steps_per_s=5432.1))
    edit(results / "soak.json", lambda d: d["services"]["gen/0"].update(end_mb=301.9))
    rc, after, _ = render(results, tmp_path, capsys)
    assert rc == 0
    assert "5,432 env steps/s" in after and "4,007 env steps/s" not in after
    assert "gen 297.3 → 301.9 MB (+0.11 %)" in after  # growth_pct is its own key


def test_modes_table_is_ebrl_bench_table(results, tmp_path, capsys):
    # The median of three repeats moves when the middle repeat does.
    def faster_ebrl(data):
        for run in data["results"]["ebrl"]:
            run["env_steps_per_s"] += 100.0

    rc, before, _ = render(results, tmp_path, capsys)
    edit(results / "bench_w1_lift.json", faster_ebrl)
    rc, after, _ = render(results, tmp_path, capsys)
    assert rc == 0
    row = next(line for line in before.splitlines() if line.startswith("| ebrl | 1.9-2.0-2.0 |"))
    steps = int(row.split(" | ")[2])
    assert f"| ebrl | 1.9-2.0-2.0 | {steps + 100} |" in after


def test_halfcheetah_seeds_table(results, tmp_path, capsys):
    for pattern in report.SEED_FILES.values():
        for path in results.glob(pattern):
            path.unlink()
    main = json.loads((results / "peer_comparison_halfcheetah.json").read_text())
    first = main["time_to_target_s"]["ebrl"]
    rc, text, _ = render(results, tmp_path, capsys)
    assert rc == 0 and "no such file is recorded yet" in text
    assert f"| min / median / max of 1 | {first:.1f} / {first:.1f} / {first:.1f} |" in text

    for seed, seconds in ((7, 150.0), (8, None)):
        per_seed = {"command": f"python benchmarks/peers/compare_halfcheetah.py --runs ebrl --ebrl-seed {seed} "
                               f"--max-seconds 400", "target_return": 1000.0, "max_seconds": 400.0,
                    "time_to_target_s": {"ebrl": seconds}, "fastest_peer": None, "speedup_over_fastest_peer": {},
                    "ebrl": json.loads(json.dumps(main["ebrl"]))}
        if seconds is None:
            per_seed["ebrl"]["summary"].pop("target_reached")
        else:
            per_seed["ebrl"]["summary"]["target_reached"]["wall_s"] = seconds
        (results / f"peer_comparison_halfcheetah_ebrl_s{seed}.json").write_text(json.dumps(per_seed))
    rc, text, _ = render(results, tmp_path, capsys)
    assert rc == 0
    assert "| 7 | 150.0 |" in text and "| 8 | not reached in 400 |" in text
    low, middle = sorted([first, 150.0])
    assert f"| min / median / max of 3 | {low:.1f} / {middle:.1f} / not reached |" in text
    fastest = main["time_to_target_s"][main["fastest_peer"]]
    assert f"**{fastest / middle:.2f}x**" in text


def test_list_shows_the_commands_it_can_rerun_and_refuses_historical_files(capsys):
    assert report.main(["--list"]) == 0
    listed = dict(line.split(": ", 1) for line in capsys.readouterr().out.splitlines())
    assert listed["bench_w1_lift"].startswith(f"{sys.executable} -m ebrl.cli bench configs/robosuite_lift.toml")
    assert listed["soak"] == f"{sys.executable} benchmarks/soak.py --minutes 30"
    assert listed["bench_w2_lift_4M"] == f"not re-runnable ({report.HISTORICAL['bench_w2_lift_4M']})"

    assert report.main(["--run", "bench_w2_lift_4M"]) == 2  # refused before anything runs
    assert "cannot re-run (an earlier W2 sizing" in capsys.readouterr().err


@pytest.mark.parametrize("tag, refused", [
    ("{{ ''.__class__.__mro__ }}", "unsafe"),
    ("{{ cmd.__globals__ }}", "unsafe"),  # a helper's module, and through it os and subprocess
    ("{{ q.__class__ }}", "unsafe"),
    ("{{ q.update({}) }}", "unsafe"),  # results are read-only
    ("{{ __import__('os').getcwd() }}", "'__import__' is undefined"),
    ("{{ open('/etc/hostname').read() }}", "'open' is undefined"),
])
def test_a_template_cannot_reach_python(tag, refused, tmp_path, capsys):
    template = tmp_path / "template.md"
    template.write_text(f'{{% call(q) section("quickstart", "quickstart_learning") %}}\n{tag}\n{{% endcall %}}\n')
    rc = report.main(["--template", str(template), "--out", str(tmp_path / "out.md")])
    err = capsys.readouterr().err
    assert rc == 2 and refused in err and f"{template}:2" in err
    assert not (tmp_path / "out.md").exists()


def test_the_environment_is_a_sandbox():
    env = report.environment()
    assert isinstance(env, SandboxedEnvironment)
    with pytest.raises(SecurityError):
        env.from_string("{{ k.__globals__ }}").render()
    with pytest.raises(UndefinedError):
        env.from_string("{{ __builtins__ }}").render()


def test_median_filters_read_one_key_and_name_a_missing_one():
    env = report.environment()
    runs = report.located({"results": {"a": [{"x": 3}, {"x": 1}, {"x": 2}], "b": [{"x": 4}, {"x": 6}]}}, "f.json")
    text = env.from_string('{{ r.results.a | median("x") }} {{ (r.results | medians("x")).b }} {{ [5, 1, 4] | median }}')
    assert text.render(r=runs) == "2 5.0 4"
    runs["results"]["b"][1].pop("x")
    with pytest.raises(report.MissingKey, match=r"f\.json: missing key 'results\.b\[1\]\.x'"):
        text.render(r=runs)


def test_reports_ahead_follow_the_curves(results, tmp_path, capsys):
    curves = json.loads((results / "learning_speed.json").read_text())["curves"]
    first_colocated = min(p["wall_s"] for p in curves["colocated"])
    before = sum(p["wall_s"] < first_colocated for p in curves["ebrl"])
    for colocated_return, ahead in ((-1e9, len(curves["ebrl"])), (1e9, before)):
        edit(results / "learning_speed.json",
             lambda d: [p.update({"return": colocated_return}) for p in d["curves"]["colocated"]])
        rc, text, _ = render(results, tmp_path, capsys)
        assert rc == 0 and f"at {ahead} of ebrl's\n{len(curves['ebrl'])} reports" in text


def test_machines_table_groups_the_files_by_machine(results, tmp_path, capsys):
    machine = json.loads((results / "quickstart_learning.json").read_text())["machine"]
    edit(results / "soak.json", lambda d: d.update(machine=machine))
    edit(results / "allocator_quality.json", lambda d: d.update(machine={"cores_seen": [2, 1.25]}))
    rc, text, _ = render(results, tmp_path, capsys)
    assert rc == 0
    assert f"| {machine} | `quickstart_learning.json`, `soak.json` |" in text
    assert "| cores seen: 2, 1.2 | `allocator_quality.json` |" in text


def test_a_missing_row_of_a_table_names_the_file(results, tmp_path, capsys):
    edit(results / "denoise_cost.json", lambda d: d.update(rows=[r for r in d["rows"] if not (
        r["layout"] == "vision" and r["batch"] == 1 and r.get("denoise_steps") == 8)]))
    rc, _, err = render(results, tmp_path, capsys)
    assert rc == 2
    assert "denoise_cost.json: no element of 'rows' with layout='vision', batch=1, policy='flow', denoise_steps=8" in err


def test_a_per_seed_file_with_another_target_is_an_error(results, tmp_path, capsys):
    edit(results / "peer_comparison_halfcheetah_ebrl_s2.json", lambda d: d.update(target_return=900.0))
    rc, _, err = render(results, tmp_path, capsys)
    assert rc == 2 and "peer_comparison_halfcheetah_ebrl_s2.json`: target_return 900.0 differs from 1000" in err
