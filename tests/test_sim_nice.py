"""``sim.nice``: the sim service and its env workers at a lower priority than generation and training."""

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


def test_the_sim_service_runs_at_its_niceness_and_the_run_finishes(tmp_path):
    code, out, seen = helpers.run_collecting_stats(tmp_path / "runs", "configs/quickstart.toml", "run.iterations=3",
                                                   "sim.nice=7", 'viz.rerun="off"', run="nice")
    assert code == 0, out
    assert {report["sim/nice"] for report in seen["sim/0"]} == {7.0}
