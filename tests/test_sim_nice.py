"""``sim.nice``: the sim service and its env workers at a lower priority than generation and training; in a process
shared with generation, only the workers."""

from __future__ import annotations

import pytest

import helpers
from ebrl import config

ROOT = helpers.ROOT


def test_a_nice_out_of_range_is_a_config_error_naming_the_field():
    raw = config.read(ROOT / "configs" / "quickstart.toml")
    raw["sim"]["nice"] = 20
    with pytest.raises(config.ConfigError, match=r"sim.nice = 20"):
        config.from_dict(raw)


@pytest.mark.slow  # two real runs (the fast suite's time, under 10 minutes on 2 cores)
@pytest.mark.parametrize("processes", ["auto", "[]"])
def test_the_env_workers_run_at_the_niceness_and_the_run_finishes(tmp_path, processes):
    """On this CPU host "auto" puts sim and gen in one process: generation's thread keeps niceness 0, the env
    workers take 7 themselves. Alone, the sim service runs at 7 too."""
    code, out, seen = helpers.run_collecting_stats(tmp_path / "runs", "configs/quickstart.toml", "run.iterations=3",
                                                   "sim.nice=7", 'viz.rerun="off"', f"run.processes={processes}",
                                                   run="nice")
    assert code == 0, out
    workers = [report["sim/workers_nice"] for report in seen["sim/0"] if "sim/workers_nice" in report]
    assert set(workers) == {7.0}  # (a report after the workers closed has none)
    assert {report["sim/nice"] for report in seen["sim/0"]} == ({0.0} if processes == "auto" else {7.0})
