"""No silent stall (issue 34): the launcher's stall watch names the stuck stage and why, restarts it, and ends the run
with a clear failure when that does not help. Unit cases on made-up reports with a fake clock; a real run whose gen
is stopped (SIGSTOP) is reported by name within a minute, restarted and finishes."""

from __future__ import annotations

import json
import signal
import time

from ebrl.bus import keys
from ebrl.messages import StatsReport
from ebrl.runview import RunView
from ebrl.stall import StallWatch
from ebrl.testing import StatsWatcher
from helpers import up

RUN = "stall"


class Clock:
    def __init__(self):
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


class Reports:
    """Each service's latest numbers, sent as reports into a RunView (a new seq each time)."""

    def __init__(self):
        self.view, self.seq = RunView(RUN), 0
        self.metrics = {
            ("sim", 0): {"sim/env_steps": 0.0},
            ("gen", 0): {"gen/envs_served": 0.0, "gen/obs_waiting_for_policy": 0.0},
            ("train", 0): {"train/updates": 0.0, "train/segments_received": 0.0, "train/update_s": 0.5,
                           "train/batch_ready": 1.0, "proc/cpu_percent": 80.0},
        }

    def send(self, *silent: str) -> None:
        for (service, instance), metrics in self.metrics.items():
            if f"{service}/{instance}" in silent:
                continue
            self.seq += 1
            self.view.on_report(keys.stats(RUN, service, instance), StatsReport(
                run=RUN, service=service, instance=instance, time=0.0, seq=self.seq, metrics=dict(metrics)))

    def move(self, *roles: str) -> None:
        names = {"sim": "sim/env_steps", "gen": "gen/envs_served", "train": "train/updates"}
        for role in roles:
            self.metrics[(role, 0)][names[role]] += 1
            if role == "sim":
                self.metrics[("train", 0)]["train/segments_received"] += 1


def run_for(watch: StallWatch, clock: Clock, reports: Reports, seconds: float, moving=(), silent=()):
    """Reports every second for ``seconds``; the first stall found, or None."""
    for _ in range(int(seconds)):
        clock.now += 1.0
        reports.move(*moving)
        reports.send(*silent)
        found = watch.check(reports.view)
        if found is not None:
            return found
    return None


def test_a_moving_run_and_a_slow_start_are_not_stalls():
    clock, reports = Clock(), Reports()
    watch = StallWatch(10.0, clock)
    assert run_for(watch, clock, reports, 60) is None  # nothing moved yet: a slow start (kernels compiling)
    assert run_for(watch, clock, reports, 60, moving=("sim", "gen", "train")) is None


def test_a_silent_instance_is_named_within_the_timeout():
    clock, reports = Clock(), Reports()
    watch = StallWatch(10.0, clock)
    run_for(watch, clock, reports, 3, moving=("sim", "gen", "train"))
    found = run_for(watch, clock, reports, 30, moving=("sim", "train"), silent=("gen/0",))
    assert found is not None and found.service == "gen/0" and "no stats report for 11 s" in found.reason


def test_no_env_steps_is_blamed_on_the_stage_that_holds_them_up():
    clock, reports = Clock(), Reports()
    watch = StallWatch(10.0, clock)
    run_for(watch, clock, reports, 3, moving=("sim", "gen", "train"))
    found = run_for(watch, clock, reports, 30, moving=("gen",))  # gen answers, the sim does not step
    assert found.service == "sim/0" and found.reason.startswith("no env steps for 11 s while generation answers")

    clock, reports = Clock(), Reports()
    watch = StallWatch(10.0, clock)
    run_for(watch, clock, reports, 3, moving=("sim", "gen", "train"))
    found = run_for(watch, clock, reports, 30, moving=("train",))  # gen answers nothing, waits for no policy
    assert found.service == "gen/0" and "generation answered no observation" in found.reason

    clock, reports = Clock(), Reports()
    watch = StallWatch(10.0, clock)
    run_for(watch, clock, reports, 3, moving=("sim", "gen", "train"))
    reports.metrics[("gen", 0)]["gen/obs_waiting_for_policy"] = 2.0  # gen waits for weights that never come
    reports.metrics[("train", 0)]["proc/cpu_percent"] = 80.0  # ... while train computes a long update: no stall
    assert run_for(watch, clock, reports, 30) is None
    reports.metrics[("train", 0)]["proc/cpu_percent"] = 0.5  # ... while train, with a full batch, computes nothing
    found = run_for(watch, clock, reports, 5)
    assert found.service == "train/0" and "holds 2 observation(s) for a newer policy" in found.reason
    reports.metrics[("train", 0)]["train/batch_ready"] = 0.0  # ... while train has no batch: segments are lost
    found = run_for(watch, clock, reports, 5)
    assert found.service == "sim/0" and "the segments do not reach it" in found.reason


def test_a_train_that_waits_while_segments_come_in_is_a_stall_and_a_second_one_fails_the_run():
    clock, reports = Clock(), Reports()
    watch = StallWatch(10.0, clock)
    run_for(watch, clock, reports, 3, moving=("sim", "gen", "train"))
    reports.metrics[("train", 0)]["proc/cpu_percent"] = 1.0
    reports.metrics[("train", 0)]["train/batch_ready"] = 0.0  # no full batch yet (a forgery keeps it from filling)
    assert run_for(watch, clock, reports, 30, moving=("sim", "gen")) is None
    reports.metrics[("train", 0)]["train/batch_ready"] = 1.0
    found = run_for(watch, clock, reports, 30, moving=("sim", "gen"))
    assert found.service == "train/0" and "while segments came in" in found.reason
    assert watch.acting(found) and watch.note() == "STALLED train/0, restarted"
    assert run_for(watch, clock, reports, 9, moving=("sim", "gen")) is None  # the restarted one starts: quiet
    again = run_for(watch, clock, reports, 30, moving=("sim", "gen"))
    assert again.service == "train/0" and not watch.acting(again)  # the restart did not help: the run fails


def test_forged_reports_standing_in_for_an_instance_at_every_look_hide_no_real_report():
    """On an open bus a peer sent, right after each of train's reports, one of its own on train's key with the
    same seq every time (the crafted-payload test; on a loaded CI machine the watch then saw only the forgery
    and restarted a train that reported every half second): arrivals are counted, not told by seq."""
    clock, reports = Clock(), Reports()
    watch = StallWatch(10.0, clock)
    key = keys.stats(RUN, "train", 0)
    for _ in range(40):
        clock.now += 1.0
        reports.move("sim", "gen", "train")
        reports.send()
        reports.view.on_report(key, StatsReport(run=RUN, service="train", instance=0, time=0.0, seq=0,
                                                metrics={"train/iteration": 1.0}))
        assert reports.view.stats[key].seq == 0  # the forgery is what the watch sees at its look
        assert watch.check(reports.view) is None
    # a report with nothing finite in it is refused whole: it never stands in for the instance's real one
    reports.send()
    real = reports.view.stats[key]
    reports.view.on_report(key, StatsReport(run=RUN, service="train", instance=0, time=0.0, seq=0,
                                            metrics={"train/policy_version": float("nan")}))
    assert reports.view.stats[key] is real


def test_zero_turns_it_off():
    clock, reports = Clock(), Reports()
    watch = StallWatch(0.0, clock)
    run_for(watch, clock, reports, 3, moving=("sim", "gen", "train"))
    assert run_for(watch, clock, reports, 100, silent=("gen/0",)) is None


def test_a_stopped_gen_is_reported_by_name_restarted_and_the_run_finishes(tmp_path):
    """SIGSTOP on gen mid-run: no error, no exit, only silence -- named within a minute (here within the 10 s
    timeout and a few seconds), killed, restarted, and every iteration done."""
    with up(tmp_path, "configs/quickstart.toml", "run.iterations=12", "train.batch_size=256", 'viz.rerun="off"',
            "run.stall_timeout=10", name="stopped") as run, StatsWatcher(run) as stats:
        stats.wait_for(lambda: (stats.latest("train/0", "train/policy_version") or 0) >= 2, 300, "policy v2")
        import psutil

        gen = next(p for p in psutil.Process(run.proc.pid).children() if "ebrl.services.gen" in " ".join(p.cmdline()))
        stopped = time.monotonic()
        gen.send_signal(signal.SIGSTOP)
        line = run.wait_for_line(lambda s: "gen/0 stalled" in s, 120, "the stall line")
        assert time.monotonic() - stopped < 60 and "no stats report" in line and "restarting it" in line
        code = run.wait(300)
    assert code == 0, run.output
    summary = json.loads((run.run_dir / "summary.json").read_text())
    assert summary["iterations"] == 12 and summary["restarts"] == {"gen/0": 1}
    events = (run.run_dir / "report" / "report.md").read_text()
    assert "stall: gen/0 stalled" in events
