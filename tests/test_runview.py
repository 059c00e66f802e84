"""What the launcher shows of a run, from stats reports and liveliness tokens alone (no bus); the progress bar also
on a real pseudo-terminal."""

from __future__ import annotations

import asyncio
import fcntl
import io
import json
import os
import pty
import struct
import sys
import termios
from pathlib import Path
from types import SimpleNamespace

from ebrl import keys
from ebrl.hosts import UNKNOWN_KEPT, HostChange, Membership
from ebrl.messages import StatsReport
from ebrl.runview import Console, Progress, RunView, may_end, summary as run_summary, write_summary
from ebrl.viz import record

import helpers

ROOT = Path(__file__).resolve().parent.parent


def report(service: str, instance: int = 0, **metrics: float) -> tuple[str, StatsReport]:
    names = {k.replace("__", "/"): v for k, v in metrics.items()}
    return keys.stats("r", service, instance), StatsReport(run="r", service=service, instance=instance, time=0.0,
                                                           seq=0, metrics=names)


def fed(*reports: tuple[str, StatsReport], **kw) -> RunView:
    view = RunView("r", **kw)
    for key, msg in reports:
        view.on_report(key, msg)
    return view


def test_metrics_add_up_over_instances_and_the_progress_line_says_training_s_numbers():
    """The progress line's return and rates are training's (issue 52): before its first report the simulators'
    rate is shown labelled as theirs, never their return."""
    now = [100.0]
    view = fed(report("sim", 0, sim__env_steps_per_s=1000.0, sim__episode_return_mean=10.0),
               report("sim", 1, sim__env_steps_per_s=500.0, sim__episode_return_mean=20.0),
               report("gen", gen__policy_version=3.0), iterations=10, clock=lambda: now[0])
    assert view.metric("sim/env_steps_per_s") == 1500.0 and view.metric("sim/episode_return_mean", "mean") == 15.0
    assert view.mean_return() is None  # the simulators' own word is not the run's return
    assert "| return - | sim 1,500 env steps/s | sim 0.0 traj/s | policy v3 |" in view.progress_line(1.0)
    for i in range(3):  # training's reports 2 s apart: 3,000 env steps and 8 segments more each time
        view.on_report(*report("train", train__policy_version=4.0, train__staleness_mean=0.5,
                               train__env_steps=3000.0 * i, train__segments_received=8.0 * i,
                               train__episode_return_mean=15.0, train__episodes=10.0 + i))
        now[0] += 2.0
    assert view.version() == 4 and view.version_floor() == 4 and not view.iterations_done()
    line = view.progress_line(3725.0, restarts=2, hosts=3)
    assert line == ("iter 4/10 (40%) | 1:02:05<1:33:07, 931.25s/it | return 15.0 | 1,500 env steps/s | 4.0 traj/s | "
                    "policy v3 | staleness 0.50 | restarts 2 | hosts 3")
    now[0] += 30.0  # training silent for longer than the rate's window: no rate made up
    assert "| 0 env steps/s | 0.0 traj/s |" in view.progress_line(3755.0)
    assert RunView("r").progress_line(0.0) == ("iter 0 | 00:00, ?it/s | return - | 0 env steps/s | 0.0 traj/s | "
                                               "policy v0 | staleness 0.00")


def test_the_rates_of_an_instance_that_left_count_no_more_until_it_reports_again():
    """A simulation host killed (its token gone): its last rate is not summed into the run's any more; its
    counts stay; a report of it after a rejoin counts again (issue 54)."""
    view = fed(report("sim", 0, sim__env_steps_per_s=1000.0, sim__env_steps=5e4),
               report("sim", 1, sim__env_steps_per_s=500.0, sim__env_steps=2e4))
    view.left("sim", 1)
    assert view.metric("sim/env_steps_per_s") == 1000.0 and view.metric("sim/env_steps") == 7e4
    assert "sim 1,000 env steps/s" in view.progress_line(1.0)
    view.on_report(*report("sim", 1, sim__env_steps_per_s=700.0, sim__env_steps=2.1e4))
    assert view.metric("sim/env_steps_per_s") == 1700.0


def test_the_progress_says_training_success_and_the_last_evaluation():
    view = fed(report("sim", sim__episode_return_mean=900.0, sim__success_rate=0.99),
               report("train", train__policy_version=40.0, train__episode_return_mean=10.0, train__success_rate=0.35,
                      train__episodes=50.0), iterations=50)
    assert "| return 10.0 | success 35% | " in view.progress_line(10.0) and "eval" not in view.progress_line(10.0)
    view.on_report(*report("eval", eval__version=40.0, eval__success_rate=0.8, eval__success_rate_lo=0.62,
                           eval__success_rate_hi=0.91, eval__return=512.34))
    assert "| success 35% | eval v40: success 80% [62%-91%], return 512.3 | " in view.progress_line(10.0)
    view.on_report(*report("eval", eval__version=45.0, eval__return=600.0))  # a task without a success check
    assert "| eval v45: return 600.0 | " in view.progress_line(10.0)
    progress = view.progress(20.0)
    assert (progress.n, progress.total) == (40, 50) and progress.line().startswith("iter 40/50 (80%) | 00:20<00:05")


def test_a_newer_report_replaces_the_instance_s_last_and_the_best_return_is_kept():
    view = fed(report("train", train__episode_return_mean=50.0, train__episodes=100.0),
               report("train", train__episode_return_mean=20.0, train__episodes=200.0),
               report("sim", sim__episode_return_mean=1e9))  # the simulator's own word moves neither
    assert view.mean_return() == 20.0 and view.best_return == 50.0


def test_the_target_return_ends_the_run_on_training_s_report_and_goes_into_the_summary(tmp_path):
    view = fed(report("sim", sim__episode_return_mean=850.0, sim__env_steps=4000.0, sim__segments=12.0),
               report("train", train__policy_version=7.0, train__episode_return_mean=840.0, train__episodes=30.0,
                      train__episode_length_max=1000.0, train__env_steps=3968.0, train__segments_received=12.0),
               target_return=900.0)
    assert view.target_reached(10.0) is None and view.reached is None
    view.on_report(*report("sim", sim__episode_return_mean=905.5, sim__env_steps=8000.0, sim__segments=30.0))
    assert view.target_reached(15.0) is None  # the simulators' own word does not end a run: training's does
    view.on_report(*report("train", train__policy_version=7.0, train__episode_return_mean=905.5,
                           train__episodes=40.0, train__episode_length_max=1000.0, train__env_steps=8000.0,
                           train__segments_received=30.0))
    assert view.target_reached(20.0) == ("reached run.target_return = 900: mean return 905.5 at iteration 7 "
                                         "after 20 s")
    summary = run_summary(view, 0, 40.0, run_dir=tmp_path, failure=None, restarts={"gen/0": 1}, host=0, hosts=[0, 1])
    line = write_summary(summary, tmp_path / "summary.json")
    assert json.loads((tmp_path / "summary.json").read_text()) == summary
    assert summary["target_reached"] == {"iteration": 7, "wall_s": 20.0, "return": 905.5, "success_rate": None}
    assert (summary["iterations"], summary["env_steps"], summary["env_steps_per_s"], summary["segments"]) == \
        (7, 8000, 200.0, 30)
    assert (summary["final_return"], summary["best_return"], summary["restarts"]) == (905.5, 905.5, {"gen/0": 1})
    assert line.startswith("run r finished: 7 iterations in 40 s, 8,000 env steps (200/s), mean return 905.5 "
                           "(best 905.5); summary in ")


def test_the_target_success_ends_the_run_too(tmp_path):
    view = fed(report("sim", sim__success_rate=0.99),
               report("train", train__policy_version=30.0, train__episode_return_mean=3.0, train__success_rate=0.85,
                      train__episodes=100.0), target_success=0.9)
    assert view.target_reached(10.0) is None
    view.on_report(*report("train", train__policy_version=30.0, train__episode_return_mean=3.0,
                           train__success_rate=0.95, train__episodes=104.0))
    assert view.target_reached(60.0) == "reached run.target_success = 0.9: success rate 95% at iteration 30 after 60 s"
    summary = run_summary(view, 0, 61.0, run_dir=tmp_path, failure=None, restarts={}, host=0, hosts=[0])
    assert summary["target_success"] == 0.9 and summary["target_reached"]["success_rate"] == 0.95


def test_training_reports_at_once_the_update_that_may_end_the_run():
    """``may_end``: what training asks after each update, to publish its report then, not an interval later."""
    run = SimpleNamespace(iterations=10, target_return=900.0, target_success=None)
    assert not may_end(run, 9, {"train/episode_return_mean": 899.0}) and may_end(run, 10, {})
    assert may_end(run, 3, {"train/episode_return_mean": 900.0})
    success = SimpleNamespace(iterations=0, target_return=None, target_success=0.9)
    assert not may_end(success, 500, {"train/success_rate": 0.85, "train/episode_return_mean": 1e9})
    assert may_end(success, 5, {"train/success_rate": 0.95})


def test_a_run_ends_on_the_update_that_reaches_its_iterations_not_a_report_interval_later(tmp_path):
    """With reports every 30 s, a run of 3 iterations ends within a few seconds of its third update: training
    reported it at once."""
    with helpers.up(tmp_path, "configs/quickstart.toml", "run.iterations=3", "run.stats_interval=30",
                    'viz.rerun="off"', name="prompt") as run:
        code = run.wait(300)
    assert code == 0, run.output[-3000:]
    rec = record.read(run.run_dir)
    last_update = max(s.end for s in rec.spans if s.lane == "train" and s.label == "update")
    stopping = next(e.time for e in rec.events if e.kind == "stopping")
    assert stopping - last_update < 15, (stopping - last_update, run.output[-2000:])


def test_a_return_that_moves_further_than_the_episodes_since_could_is_not_taken():
    first = dict(train__policy_version=5.0, train__episode_return_mean=10.0, train__success_rate=0.1,
                 train__episodes=50.0, train__episode_length_max=100.0)
    view = fed(report("train", **first), target_return=500.0, target_success=0.9, max_abs_reward=1.0)
    # no episode finished since, yet the return moved: refused, and it cannot end the run
    view.on_report(*report("train", **{**first, "train__episode_return_mean": 600.0}))
    # one new episode moves a mean of 20 by at most 1/20 of twice the largest return (100 steps of 1): 10
    view.on_report(*report("train", **{**first, "train__episode_return_mean": 25.0, "train__episodes": 51.0}))
    view.on_report(*report("train", **{**first, "train__success_rate": 0.95, "train__episodes": 51.0}))
    # more than an episode of 100 steps can return at all
    view.on_report(*report("train", **{**first, "train__episode_return_mean": 101.0, "train__episodes": 200.0}))
    assert view.returns_refused == 4 and view.target_reached(1.0) is None
    view.on_report(*report("train", **{**first, "train__episode_return_mean": 19.0, "train__episodes": 51.0}))
    assert view.returns_refused == 4 and view.trained["train/episode_return_mean"] == 19.0  # within the bound
    view.on_report(*report("train", **{**first, "train__episode_return_mean": 3.0, "train__episodes": 0.0}))
    assert view.trained["train/episodes"] == 0.0  # a trainer that started again counts from 0
    view.on_report(*report("sim", sim__episode_return_mean=1e9, sim__success_rate=1.0))  # sim's own, however high
    assert view.target_reached(2.0) is None


def test_the_run_s_numbers_are_training_s_and_the_simulator_s_are_shown_as_its_own(tmp_path):
    """Issue 52: a simulator that reports a return of 1e9 and frozen env steps (its credential may) moves none of
    the run's numbers: the progress line, summary.json and its end line take them from training; the summary
    keeps the simulator's own under ``sim``, as its word."""
    view = fed(report("train", train__policy_version=12.0, train__episode_return_mean=150.0, train__episodes=80.0,
                      train__success_rate=0.25, train__episode_length_max=200.0, train__env_steps=24_576.0,
                      train__segments_received=768.0),
               report("sim", sim__episode_return_mean=1e9, sim__success_rate=1.0, sim__env_steps=10.0,
                      sim__episodes=1e6, sim__segments=3.0, sim__env_steps_per_s=1e7),
               iterations=30, max_abs_reward=1.0)
    line = view.progress_line(12.0)
    assert "| return 150.0 | success 25% | " in line and "1e9" not in line and "1,000,000,000" not in line
    summary = run_summary(view, 0, 12.0, run_dir=tmp_path, failure=None, restarts={}, host=0, hosts=[0])
    assert (summary["env_steps"], summary["episodes"], summary["segments"], summary["env_steps_per_s"]) == \
        (24_576, 80, 768, 2048.0)
    assert (summary["final_return"], summary["best_return"], summary["final_success_rate"]) == (150.0, 150.0, 0.25)
    assert summary["sim"] == {"env_steps": 10.0, "episodes": 1e6, "segments": 3.0, "episode_return_mean": 1e9,
                              "success_rate": 1.0, "env_steps_per_s": 1e7}
    end = write_summary(summary, tmp_path / "summary.json")
    assert "24,576 env steps (2,048/s), mean return 150.0 (best 150.0)" in end


def test_a_restarted_trainer_neither_drops_nor_jumps_the_run_s_counts(tmp_path):
    """A restarted train counts from 0 again: the run's env steps, episodes and segments go on from where the
    last trainer's ended, and the rate on the progress line neither goes negative nor leaps."""
    now = [0.0]
    view = RunView("r", clock=lambda: now[0])

    def train(steps: float, episodes: float, ret: float = 100.0) -> None:
        view.on_report(*report("train", train__policy_version=3.0, train__env_steps=steps,
                               train__segments_received=steps / 32, train__episodes=episodes,
                               train__episode_return_mean=ret))
        now[0] += 1.0

    for i in range(6):
        train(1024.0 * i, 4.0 * i)
    assert view.train_count("train/env_steps") == 5120.0 and view.train_count("train/episodes") == 20.0
    train(0.0, 0.0, ret=90.0)  # the restarted trainer's first report
    assert view.train_count("train/env_steps") == 5120.0 and view.train_count("train/episodes") == 20.0
    for i in range(1, 4):
        train(1024.0 * i, 4.0 * i, ret=90.0)
        assert view.train_count("train/env_steps") == 5120.0 + 1024.0 * i
        rate = float(view.progress_line(now[0]).split(" env steps/s")[0].rsplit("| ", 1)[1].replace(",", ""))
        assert 800.0 <= rate <= 1024.0, rate  # the second without steps (the restart) in it, no drop below 0
    summary = run_summary(view, 0, 10.0, run_dir=tmp_path, failure=None, restarts={"train/0": 1}, host=0, hosts=[0])
    assert (summary["env_steps"], summary["episodes"], summary["segments"]) == (8192, 32, 256)
    assert (summary["final_return"], summary["best_return"]) == (90.0, 100.0)


def test_a_counter_moves_in_any_report_between_looks_and_not_by_repeating_itself():
    """For the stall watch (``RunView.moves``): the real reports' new values count though a flood of frozen ones
    on the same key is the latest at every look; two values that alternate (a frozen flood between the real,
    stuck ones) are no movement; the first value is where the counter starts."""
    view, key = RunView("r"), keys.stats("r", "gen", 0)
    for served in range(5):
        view.on_report(*report("gen", gen__envs_served=float(served)))
        for _ in range(50):
            view.on_report(*report("gen", gen__envs_served=7.0))
    assert view.stats[key].metrics["gen/envs_served"] == 7.0 and view.moves[(key, "gen/envs_served")] == 5
    for _ in range(100):
        view.on_report(*report("gen", gen__envs_served=4.0))
        view.on_report(*report("gen", gen__envs_served=7.0))
    assert view.moves[(key, "gen/envs_served")] == 5
    fresh = fed(report("gen", gen__envs_served=3.0))
    assert (key, "gen/envs_served") not in fresh.moves


def test_a_stopped_run_says_so_and_has_no_return_yet(tmp_path):
    summary = run_summary(RunView("r"), 143, 0.0, run_dir=tmp_path, failure="x", restarts={}, host=0, hosts=[0])
    line = write_summary(summary, tmp_path / "summary.json")
    assert summary["env_steps_per_s"] == 0.0 and summary["target_reached"] is None
    assert line.startswith("run r stopped: 0 iterations") and "mean return - (best -)" in line


def test_the_console_prints_progress_every_few_seconds_off_a_terminal():
    out = io.StringIO()
    console = Console(out)
    console.progress(Progress(1, 4, 2.0, "first"))
    console.progress(Progress(2, 4, 3.0, "too soon"))
    console.progress(Progress(3, 4, 4.0, "forced"), force=True)
    console.say("\nebrl: something happened")
    assert out.getvalue() == ("iter 1/4 (25%) | 00:02<00:06,  2.00s/it | first\n"
                              "iter 3/4 (75%) | 00:04<00:01,  1.33s/it | forced\n\nebrl: something happened\n")
    assert "\r" not in out.getvalue() and "\033" not in out.getvalue()  # plain lines: a log stays readable


def test_on_a_terminal_the_progress_is_a_tqdm_bar_that_fits_the_width(tmp_path):
    """A real pseudo-terminal 80 columns wide: every redraw of the bar fits it, shows the percentage, the ETA and
    the rate, and the run's numbers start with the return; a line said meanwhile is printed whole."""
    script = tmp_path / "bar.py"
    script.write_text(
        "import sys, time\n"
        "from ebrl.runview import Console, Progress\n"
        "c = Console(sys.stdout)\n"
        "fields = 'return 15.0 | success 35% | eval v4: success 80% [62%-91%], return 512.3 | 1,500 env steps/s'\n"
        "for i in range(4):\n"
        "    c.progress(Progress(i, 10, 60.0 + 10 * i, fields))\n"
        "    time.sleep(0.05)\n"
        "c.say('ebrl: a line said while the bar is drawn')\n"
        "c.end_progress()\n"
        "c.say('after the bar')\n")
    pid, fd = pty.fork()
    if pid == 0:  # the child: its stdout is the terminal
        os.execve(sys.executable, [sys.executable, str(script)],
                  {**os.environ, "PYTHONPATH": str(ROOT), "COLUMNS": "", "LINES": ""})
    fcntl.ioctl(fd, termios.TIOCSWINSZ, struct.pack("HHHH", 24, 80, 0, 0))
    out = b""
    while True:
        try:
            data = os.read(fd, 4096)
        except OSError:
            break
        if not data:
            break
        out += data
    _, status = os.waitpid(pid, 0)
    assert status == 0, out
    text = out.decode()
    redraws = [part for line in text.split("\n") for part in line.split("\r") if part.startswith("iter ")]
    assert redraws and all(len(part.rstrip()) <= 80 for part in redraws), redraws
    last = redraws[-1]
    assert last.startswith("iter 3/10  30%|") and "<" in last and "/it" in last and "return 15.0" in last, last
    assert "ebrl: a line said while the bar is drawn\r\n" in text and text.rstrip().endswith("after the bar")


def test_membership_reports_hosts_joining_and_leaving_and_a_lost_primary():
    members = Membership("r", me=1, multi=True, lost_after_s=30.0)
    assert members.update(keys.live("r", "launcher", 1), True) is None  # itself
    assert members.update(keys.live("r", "sim", 1), True) is None
    assert members.update(keys.live("r", "launcher", 0), True) == HostChange(0, joined=True)
    assert members.update(keys.live("r", "launcher", 0), True) is None  # already up
    assert members.update(keys.live("r", "train", 0), True) is None
    assert members.is_live("sim", 1) and members.services_live() == 2 and members.hosts() == [0, 1]
    assert not members.primary_lost(now=100.0)
    members.update(keys.live("r", "train", 0), False)
    assert members.update(keys.live("r", "launcher", 0), False) == HostChange(0, joined=False)
    assert not members.primary_lost(now=129.0) and members.primary_lost(now=130.0)
    assert members.hosts() == [0, 1]  # every host that took part
    members.update(keys.live("r", "launcher", 2), True)
    members.ending = True
    assert members.update(keys.live("r", "launcher", 2), False) is None  # leaving while this host stops


def test_membership_admitting_only_the_planned_instances_counts_every_other_token_and_takes_none_in():
    members = Membership("r", me=0, multi=True)
    members.admit_only((("sim", 0), ("train", 0), ("launcher", 0), ("launcher", 1)))
    members.update(keys.live("r", "sim", 0), True)
    for n in (1, 2, 2):  # a host that is not in the plan, twice
        assert members.update(keys.live("r", "sim", n), True) is None
    assert members.update(keys.live("r", "launcher", 5), True) is None  # no host joined: not planned
    assert members.update("ebrl/live/r/**", True) is None  # a wildcard token
    assert members.unknown_seen == 4 and members.services_live() == 1 and members.hosts() == [0]
    members.update(keys.live("r", "sim", 2), False)
    members.update(keys.live("r", "sim", 2), True)  # it came back: counted again
    assert members.unknown_seen == 5 and not members.is_live("sim", 2)
    assert members.update(keys.live("r", "launcher", 1), True) == HostChange(1, joined=True)
    for n in range(100, 100 + UNKNOWN_KEPT + 500):  # a flood of them: counted, remembered only so far
        members.update(keys.live("r", "sim", n), True)
    assert members.unknown_seen == 5 + UNKNOWN_KEPT + 500 and len(members.unknown) == UNKNOWN_KEPT


def test_a_host_number_is_taken_when_another_launcher_has_it_live():
    members = Membership("r", me=1, multi=True)
    assert not asyncio.run(members.number_taken(wait_s=0.0))
    members.update(keys.live("r", "launcher", 1), True)  # a launcher elsewhere with this host's number
    assert asyncio.run(members.number_taken(wait_s=0.0))
    one = Membership("r")
    assert one.update(keys.live("r", "launcher", 3), True) is None and one.hosts() == [0]  # a one-host run
