"""ebrl.testing, the harness of tests, `ebrl bench` and benchmarks/: the name a run really gets, and one real
quickstart run started, watched and stopped through it."""

import time

import pytest

from ebrl.testing import Run, RunError, StatsWatcher, run_name, up_command, up_sets
from helpers import ROOT

QUICKSTART = ROOT / "configs" / "quickstart.toml"


def test_a_run_name_among_the_overrides_wins_over_the_name_asked_for(tmp_path):
    # `ebrl bench CONFIG --set run.name=X` once watched bench's own name and waited 300 s for a run called X
    asked = up_sets(tmp_path, 7447, name="bench-ebrl")
    assert run_name(QUICKSTART, asked) == "bench-ebrl"
    renamed = up_sets(tmp_path, 7447, name="bench-ebrl", overrides=["run.mode=ebrl", "run.name=mine"])
    assert run_name(QUICKSTART, renamed) == "mine"
    assert run_name(QUICKSTART, up_sets(tmp_path, 7447)) == "quickstart"  # no name asked: the config's
    cmd = up_command(QUICKSTART, renamed, ["--only", "sim"])
    assert cmd[cmd.index("up"):cmd.index("up") + 4] == ["up", str(QUICKSTART), "--only", "sim"]
    assert cmd[-2:] == ["--set", "run.name=mine"]  # last, as ebrl up applies them: in order


@pytest.mark.slow  # the fast suite's 10 minutes; the fast suite's time
def test_a_renamed_run_is_watched_under_its_real_name_and_stops_on_sigint(tmp_path):
    with Run(QUICKSTART, "run.iterations=0", "train.batch_size=256", 'viz.rerun="off"', "run.name=renamed",
             name="asked", out_dir=tmp_path) as run, StatsWatcher(run) as stats:
        assert run.name == "renamed"
        stats.wait_for(lambda: (stats.latest("train/0", "train/policy_version") or 0) >= 1, 300,
                       "the first policy update")
        assert run.run_dir.parent == tmp_path and run.run_dir.name.startswith("renamed-")
        with pytest.raises(RunError, match="gave up waiting for a metric nobody reports after 0.5 s"):
            stats.wait_for(lambda: stats.latest("sim/0", "no/such_metric") is not None, 0.5, "a metric nobody reports")
        code = run.stop()
        with pytest.raises(RunError, match="the run ended while waiting for more(.|\n)*run renamed stopped"):
            stats.wait_for(lambda: False, 60, "more")  # names the exit and ends with the run's output
    assert code == 130
    window = stats.between(time.time() - 3600, time.time())
    assert {"sim/0", "gen/0", "train/0"} <= set(window)
    assert not stats.between(time.time() + 60, time.time() + 120)  # a window that no report falls into
