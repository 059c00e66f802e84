"""``ebrl sweep`` on Optuna: the sweep file and its errors, the objective read from a run's stats, pruning from a
fed curve, the budget shared by several processes, the results table and plots, and the best trial's config read
back by the config checker (fast); then real sweeps of the quickstart (slow): 8 trials 2 at a time on SQLite with
pruning, Ctrl-C and a resume that redoes no finished trial, a second process on the same storage; a metric no
run publishes; the same study on a PostgreSQL server the test starts."""

from __future__ import annotations

import csv
import glob
import importlib.util as importlib_util
import json
import os
import pwd
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

optuna = pytest.importorskip("optuna", reason="the sweep extra is not installed (pip install -e '.[sweep]')")
from optuna.trial import TrialState  # noqa: E402

from ebrl import cli, config as config_mod  # noqa: E402
from ebrl.messages import StatsReport  # noqa: E402
from ebrl.sweep import results, runner, spec  # noqa: E402
from ebrl.sweep.curve import Curve, report_and_check  # noqa: E402
from ebrl.sweep.spec import Objective, SweepError  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
pytestmark = [pytest.mark.filterwarnings("ignore::optuna.exceptions.ExperimentalWarning"),
              pytest.mark.filterwarnings("ignore:Heartbeat of storage is supposed to be used with Study.optimize")]

SWEEP_FILE = """
config = "base.toml"
study = "Unit Sweep"
n_trials = 6

[set]
run.seed = 3
"sim.envs_per_group" = 4

[params]
train.lr = {log_uniform = [1e-4, 3e-3]}
"algo.clip" = {uniform = [0.1, 0.3], step = 0.05}
algo.epochs = {int = [4, 12], step = 4}
algo.minibatches = {log_int = [2, 8]}
policy.hidden = {choice = [[64, 64], [128, 128]]}

[objective]
metric = "train/episode_return_mean"
reduce = "mean_last"
last_n = 3

[budget]
iterations = 7
"""


def write_sweep(tmp_path: Path, text: str = SWEEP_FILE) -> Path:
    (tmp_path / "base.toml").write_text('base = "%s"\n[run]\nname = "mine"\n' % (ROOT / "configs" / "quickstart.toml"))
    path = tmp_path / "unit.toml"
    path.write_text(text)
    return path


def report(service: str, metrics: dict[str, float], instance: int = 0) -> StatsReport:
    return StatsReport(run="r", service=service, instance=instance, time=0.0, seq=0, metrics=metrics)


def train_curve(values: list[float], start: int = 1, every: int = 1) -> list[StatsReport]:
    """Training's reports of a run whose return after update ``start + i * every`` is ``values[i]``."""
    return [report("train", {"train/updates": start + i * every, "train/episode_return_mean": v})
            for i, v in enumerate(values)]


# --- the sweep file -------------------------------------------------------------------------------------------


def test_a_sweep_file_reads_dotted_and_quoted_keys_every_distribution_and_checks_against_the_config(tmp_path):
    sweep = spec.load(str(write_sweep(tmp_path)), sets=["algo.gamma=0.98"])
    assert sweep.config == str((tmp_path / "base.toml").resolve())  # relative to the sweep file
    assert sweep.study == "Unit Sweep" and sweep.directory == Path("sweeps/unit-sweep")
    assert sweep.storage == f"sqlite:///{Path('sweeps/unit-sweep/study.db').resolve()}"
    kinds = {p.key: (p.kind, p.low, p.high, p.step, p.choices) for p in sweep.params}
    assert kinds == {"train.lr": ("log_uniform", 1e-4, 3e-3, None, ()),
                     "algo.clip": ("uniform", 0.1, 0.3, 0.05, ()),
                     "algo.epochs": ("int", 4, 12, 4, ()),
                     "algo.minibatches": ("log_int", 2, 8, None, ()),
                     "policy.hidden": ("choice", None, None, None, ([64, 64], [128, 128]))}
    assert sweep.overrides() == ["run.seed=3", "sim.envs_per_group=4", "algo.gamma=0.98", "run.iterations=7"]
    cfg = spec.check(sweep)
    assert (cfg.run.name, cfg.run.iterations, cfg.sim.envs_per_group, cfg.algo.gamma) == ("mine", 7, 4, 0.98)

    trial = optuna.create_study().ask()
    values = {p.key: p.suggest(trial) for p in sweep.params}
    assert 1e-4 <= values["train.lr"] <= 3e-3 and values["algo.epochs"] in (4, 8, 12)
    assert round(values["algo.clip"] / 0.05, 6).is_integer() and 2 <= values["algo.minibatches"] <= 8
    assert values["policy.hidden"] in ([64, 64], [128, 128])  # a list, stored by Optuna as JSON text
    assert trial.params["policy.hidden"] in ("[64, 64]", "[128, 128]")
    sets = sweep.trial_overrides("unit-t0000", values)
    loaded = config_mod.load(sweep.config, sets)
    assert loaded.policy.hidden == values["policy.hidden"] and loaded.train.lr == values["train.lr"]
    assert loaded.run.name == "unit-t0000" and loaded.run.output_dir == str((sweep.directory / "trials").resolve())


@pytest.mark.parametrize("text, said", [
    ('train.lrr = {log_uniform = [1e-4, 3e-3]}', "params.train.lrr = 0.0001: unknown key train.lrr (did you mean train.lr?)"),
    ('rum.seed = {int = [0, 3]}', "params.rum.seed = 0: unknown section [rum]"),
    ('train.lr = {loguniform = [1e-4, 3e-3]}', "params.train.lr: distribution loguniform (did you mean log_uniform?)"),
    ('train.lr = {log_uniform = [3e-3, 1e-4]}', "params.train.lr: log_uniform = [0.003, 0.0001]: low must be below high"),
    ('train.lr = {log_uniform = [0, 1e-3]}', "params.train.lr: log_uniform = [0, 0.001]: a log scale needs low > 0"),
    ('train.lr = {log_uniform = [1e-4, 1e-3], step = 1e-4}', "params.train.lr: step with log_uniform"),
    ('algo.epochs = {int = [4.5, 12]}', "params.algo.epochs: int = [4.5, 12]: [low, high], two integers"),
    ('algo.epochs = {uniform = [4, 12]}', "params.algo.epochs = 4.0: algo.epochs: expected an integer"),
    ('policy.hidden = {choice = []}', "params.policy.hidden: choice = []: a non-empty list"),
    ('train.lr = 0.001', "params.train.lr = 0.001: a distribution"),
    ('train.batch_size = {int = [100, 2048]}', "params.train.batch_size = 100: train.batch_size = 100: must be a multiple"),
])
def test_a_bad_param_is_an_error_that_names_it(tmp_path, text, said):
    path = write_sweep(tmp_path, f'config = "quickstart"\n[params]\n{text}\n')
    with pytest.raises(SweepError) as caught:
        spec.check(spec.load(str(path)))
    assert said in str(caught.value)


@pytest.mark.parametrize("text, said", [
    ('config = "quickstart"\nn_trails = 3', "unknown key n_trails (did you mean n_trials?)"),
    ('config = "quickstart"\n[objective]\nreduce = "max"', "objective.reduce = 'max': one of last, best, mean_last"),
    ('config = "quickstart"\n[objective]\nmetric = "return"', "objective.metric = 'return': a metric"),
    ('config = "quickstart"\n[budget]\nminutes = 3', "unknown key budget.minutes; known: iterations, seconds"),
    ('config = "quickstart"\n[set]\nrun.name = "x"', "run.name: the sweep names each trial's run"),
    ('config = "nosuch"', "config nosuch with the sweep's [set] and budget: nosuch: no such file"),
    ('n_trials = 3', "unit.toml: a sweep file (params, n_trials) needs `config = ...`"),
    ('config = "quickstart"\n[set]\nrun.iterations = 0', "run.iterations = 0 runs until Ctrl-C; give each trial a "
                                                          "budget"),
])
def test_a_bad_sweep_file_is_an_error_that_names_the_key(tmp_path, text, said):
    path = write_sweep(tmp_path, text + '\n[params]\ntrain.lr = {log_uniform = [1e-4, 3e-3]}\n')
    with pytest.raises(SweepError) as caught:
        spec.check(spec.load(str(path)))
    assert said in str(caught.value)


def test_param_flags_and_a_config_swept_by_flags_alone():
    assert spec.parse_param_flag("train.lr=log_uniform:1e-4,3e-3") == ("train.lr", {"log_uniform": [1e-4, 3e-3]})
    assert spec.parse_param_flag("algo.epochs=int:4,16,4") == ("algo.epochs", {"int": [4, 16], "step": 4})
    assert spec.parse_param_flag("policy.hidden=choice:[64,64],[128,128]") == (
        "policy.hidden", {"choice": [[64, 64], [128, 128]]})
    assert spec.parse_param_flag("run.mode=choice:ebrl,async") == ("run.mode", {"choice": ["ebrl", "async"]})
    assert spec.parse_param_flag("algo.clip={uniform = [0.1, 0.3]}") == ("algo.clip", {"uniform": [0.1, 0.3]})
    with pytest.raises(SweepError, match="--param 'train.lr': expected KEY=DIST"):
        spec.parse_param_flag("train.lr")
    sweep = spec.load("quickstart", params=["train.lr=log_uniform:1e-4,3e-3"], sets=["run.seed=2"], n_trials=4,
                      iterations=5, metric="train/value_loss", direction="minimize", jobs=3)
    assert (sweep.study, sweep.n_trials, sweep.jobs, sweep.budget.iterations) == ("quickstart", 4, 3, 5)
    assert sweep.objective == Objective(metric="train/value_loss", direction="minimize")
    assert sweep.overrides() == ["run.seed=2", "run.iterations=5"] and [p.key for p in sweep.params] == ["train.lr"]


def test_jobs_and_core_slots_follow_the_cores():
    assert spec.default_jobs(2, cores=16) == 8 and spec.default_jobs(2, cores=2) == 1 and spec.default_jobs(4, 3) == 1
    assert spec.core_slots(3, 2, list(range(8))) == [[0, 1], [2, 3], [4, 5]]
    assert spec.core_slots(2, 2, [0, 1]) == [None, None]  # do not fit: every trial may use every core
    assert spec.core_slots(1, 2, list(range(8))) == [None]


# --- the objective and pruning --------------------------------------------------------------------------------


def test_the_objective_is_read_from_stats_reports_at_every_training_update():
    reports = [report("train", {"train/updates": 0}), report("sim", {"sim/episode_return_mean": 99.0}),
               *train_curve([10.0, 30.0, 20.0], start=1, every=2),  # updates 1, 3, 5
               report("train", {"train/updates": 9, "train/episode_return_mean": 40.0}, instance=1),  # another rank
               report("train", {"train/updates": 5, "train/episode_return_mean": 25.0})]  # later, at the same update
    curve = Curve(Objective()).feed_all(reports)
    assert curve.points == {1: 10.0, 3: 30.0, 5: 25.0} and curve.updates == 5
    assert curve.value() == 25.0
    assert Curve(Objective(reduce="best")).feed_all(reports).value() == 30.0
    assert Curve(Objective(reduce="best", direction="minimize")).feed_all(reports).value() == 10.0
    assert Curve(Objective(reduce="mean_last", last_n=2)).feed_all(reports).value() == 27.5
    assert curve.new_steps() == [1, 2, 3, 4, 5] and curve.new_steps() == []  # every step once, gaps filled
    sim = Curve(Objective(metric="sim/episode_return_mean")).feed_all(reports)
    assert sim.points == {0: 99.0}  # a sim metric at the training update it arrived at
    missing = Curve(Objective(metric="train/episode_returns_mean")).feed_all(reports)
    assert missing.value() is None
    assert "train/episode_returns_mean was never published by train during the run (5 training updates) " \
           "(closest published: train/episode_return_mean" in missing.missing()


def test_pruning_follows_the_median_of_completed_curves():
    study = optuna.create_study(direction="maximize",
                                pruner=optuna.pruners.MedianPruner(n_startup_trials=2, n_warmup_steps=2))

    def fed(values: list[float]) -> tuple[optuna.Trial, list[int]]:
        trial, curve, pruned_at = study.ask(), Curve(Objective()), []
        for r in train_curve(values):
            curve.feed(r)
            if report_and_check(trial, curve):
                pruned_at.append(curve.updates)
        return trial, pruned_at

    for values in ([10, 20, 30, 40, 50], [12, 22, 32, 42, 52]):
        trial, pruned_at = fed(values)
        assert pruned_at == []  # fewer than n_startup_trials complete: nothing is pruned
        study.tell(trial, values[-1])
    worse, pruned_at = fed([30, 30, 5, 5, 5])  # ahead first, within the warm-up; then below the median
    assert pruned_at[0] == 3
    better, pruned_at = fed([11, 21, 31, 45, 60])
    assert pruned_at == []
    assert sorted(worse.storage.get_trial(worse._trial_id).intermediate_values) == [1, 2, 3, 4, 5]


# --- the study's budget over several processes ----------------------------------------------------------------


def test_the_budget_counts_finished_and_earlier_running_trials_and_finds_a_dead_sweeps_trials():
    study = optuna.create_study()
    for value in (1.0, 2.0):
        study.tell(study.ask(), value)
    pruned = study.ask()
    study.tell(pruned, state=TrialState.PRUNED)
    study.tell(study.ask(), state=TrialState.FAIL)
    late = [study.ask() for _ in range(3)]  # numbers 4, 5, 6, running
    trials = study.get_trials(deepcopy=False)
    assert runner.counts(trials) == (3, 3)
    assert not runner.surplus(trials, 4, 5) and not runner.surplus(trials, 5, 5) and runner.surplus(trials, 6, 5)
    assert not runner.surplus(trials, 6, 6)

    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    for trial, pid in zip(late, (dead.pid, os.getppid(), os.getpid())):
        trial.set_user_attr("worker", f"here:{pid}")
    trials = study.get_trials(deepcopy=False)
    gone = runner.gone_here(trials, "here", os.getpid(), mine={6})
    assert [t.number for t in gone] == [4]  # its process exited; the parent lives; trial 6 is this one's
    assert [t.number for t in runner.gone_here(trials, "here", os.getpid(), mine=set())] == [4, 6]
    assert runner.gone_here(trials, "elsewhere", os.getpid(), mine=set()) == []  # another host's: its heartbeat

    runner.requeue(study, trials[4])
    waiting = study.get_trials(deepcopy=False, states=(TrialState.WAITING,))
    assert len(waiting) == 1 and waiting[0].user_attrs == {"retry_of": 4}


def test_a_trial_whose_heartbeat_stopped_is_failed_and_queued_again(tmp_path, monkeypatch):
    monkeypatch.setattr(runner, "HEARTBEAT_S", 1)
    monkeypatch.setattr(runner, "GRACE_S", 1)
    study = optuna.create_study(storage=runner.open_storage(f"sqlite:///{tmp_path / 'study.db'}"))
    trial = study.ask()
    trial.suggest_float("train.lr", 1e-4, 3e-3, log=True)
    with runner.Heartbeat(study._storage, trial._trial_id):
        time.sleep(1.5)  # beating: not stale
        optuna.storages.fail_stale_trials(study)
        assert study.get_trials()[0].state == TrialState.RUNNING
    time.sleep(2.2)  # its sweep died: no beat for longer than the grace period
    optuna.storages.fail_stale_trials(study)
    (stale, retry) = study.get_trials()
    assert stale.state == TrialState.FAIL and retry.state == TrialState.WAITING
    assert retry.system_attrs["fixed_params"] == stale.params and retry.user_attrs == {"retry_of": 0}


# --- results and the best config ------------------------------------------------------------------------------


def a_study_with(tmp_path: Path, complete: list[tuple[float, float, float]]):
    """A sweep of the quickstart over lr and clip, its SQLite study holding ``complete`` (lr, clip, value), a pruned
    trial with a curve, and a failed one."""
    sweep = spec.load("quickstart", params=["train.lr=log_uniform:1e-4,3e-3", "algo.clip=uniform:0.1,0.3"],
                      directory=str(tmp_path / "sw"), study="results")
    sweep.directory.mkdir(parents=True)
    study = runner.open_study(sweep, spec.check(sweep))
    dists = {p.key: optuna.distributions.FloatDistribution(p.low, p.high, log=p.kind == "log_uniform")
             for p in sweep.params}
    for lr, clip, value in complete:
        study.add_trial(optuna.trial.create_trial(
            params={"train.lr": lr, "algo.clip": clip}, distributions=dists, value=value,
            intermediate_values={1: value / 2, 2: value}, user_attrs={"run_dir": str(sweep.directory / "trials/x"),
                                                                      "seconds": 12.5, "worker": "h:1"}))
    study.add_trial(optuna.trial.create_trial(
        state=TrialState.PRUNED, params={"train.lr": 1e-4, "algo.clip": 0.1}, distributions=dists,
        intermediate_values={1: 1.0, 2: 2.0, 3: 2.5}, user_attrs={"note": "pruned at training update 3"}))
    study.add_trial(optuna.trial.create_trial(
        state=TrialState.FAIL, params={"train.lr": 2e-4, "algo.clip": 0.2}, distributions=dists,
        user_attrs={"failure": "ebrl up exited 1: a | b"}))
    return sweep, study


def test_the_results_table_and_plots_say_when_there_are_too_few_trials_for_importance(tmp_path):
    sweep, study = a_study_with(tmp_path, [(1e-3, 0.2, 30.0)])
    lines = results.write_all(study, sweep)
    assert "(parameter importance: needs at least 3 complete trials (1 so far))" in [line.strip() for line in lines]
    rows = list(csv.DictReader(open(sweep.directory / "results.csv")))
    assert [(r["trial"], r["state"], r["objective"], r["update"]) for r in rows] == [
        ("0", "complete", "30.0", "2"), ("1", "pruned", "2.5", "3"), ("2", "fail", "", "")]
    assert rows[0]["train.lr"] == "0.001" and rows[2]["note"] == "ebrl up exited 1: a | b"
    md = (sweep.directory / "results.md").read_text()
    assert "| 0 | complete | 0.001 | 0.2 | 30 | 2 | 12.5 | trials/x | h:1 |  |" in md
    assert "| 2 | fail | 0.0002 | 0.2 |  |  |  |  |  | ebrl up exited 1: a \\| b |" in md
    assert "Best: trial 0, 30: train.lr=0.001 algo.clip=0.2" in md and "![optimisation history](history.png)" in md
    assert (sweep.directory / "history.png").stat().st_size > 1000 and (sweep.directory / "curves.png").is_file()
    assert not (sweep.directory / "importance.png").exists()

    more, study = a_study_with(tmp_path / "more", [(1e-3, 0.2, 30.0), (2e-3, 0.15, 40.0), (1.5e-4, 0.28, 5.0)])
    results.write_all(study, more)
    assert (more.directory / "importance.png").stat().st_size > 1000
    assert "![parameter importance](importance.png)" in (more.directory / "results.md").read_text()


def test_the_best_config_is_a_config_ebrl_up_takes(tmp_path, capsys):
    sweep, study = a_study_with(tmp_path, [(1e-3, 0.2, 30.0), (2.5e-3, 0.12, 41.5), (1.5e-4, 0.28, 5.0)])
    text = results.best_config(study, sweep)
    assert text.startswith("# The best trial of sweep results: trial 1, train/episode_return_mean = 41.5")
    path = tmp_path / "best.toml"
    path.write_text(text)
    assert cli.main(["config", str(path)]) == 0  # `ebrl config FILE`: the check ebrl up makes
    cfg = config_mod.load(str(path))
    assert (cfg.train.lr, cfg.algo.clip, cfg.run.name, cfg.run.iterations) == (2.5e-3, 0.12, "quickstart", 400)

    empty = spec.load("quickstart", params=["train.lr=log_uniform:1e-4,3e-3"], directory=str(tmp_path / "e"))
    empty.directory.mkdir()
    with pytest.raises(SweepError, match="no complete trial yet"):
        results.best_config(runner.open_study(empty, spec.check(empty)), empty)


def test_without_optuna_ebrl_sweep_says_how_to_install_it(monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "optuna", None)  # `import optuna` raises ImportError
    assert cli.main(["sweep", "quickstart", "--param", "train.lr=log_uniform:1e-4,3e-3"]) == 2
    assert "pip install 'ebrl[sweep]'" in capsys.readouterr().err


def test_ebrl_help_does_not_import_optuna():
    code = "import sys; from ebrl import cli; cli.parser(); print('optuna' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, cwd=ROOT)
    assert out.stdout.strip() == "False", out.stderr


# --- real sweeps of the quickstart (slow) ---------------------------------------------------------------------

ACCEPTANCE = """
config = "quickstart"
study = "acceptance"
n_trials = 8

[params]
train.lr = {log_uniform = [1e-4, 3e-3]}
algo.clip = {uniform = [0.1, 0.3]}

[objective]
metric = "train/episode_return_mean"

[budget]
iterations = 6
"""
FINISHED = (TrialState.COMPLETE, TrialState.PRUNED)
WAIT_S = 1800  # for progress of real trials on a loaded 2-core machine


def start_sweep(sweep_file: Path, directory: Path, *args: str, log: Path) -> subprocess.Popen:
    """``ebrl sweep SWEEP_FILE --dir DIRECTORY ARGS`` as a user runs it, its output in ``log``."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in (str(ROOT), os.environ.get("PYTHONPATH")) if p)}
    with open(log, "w") as out:
        return subprocess.Popen([sys.executable, "-m", "ebrl.cli", "sweep", str(sweep_file), "--dir", str(directory),
                                 *args], cwd=directory.parent, stdout=out, stderr=subprocess.STDOUT, env=env)


class Study:
    """The sweep's study as another process sees it in the storage, opened once a sweep has made it (it has printed
    its first lines: the study so far)."""

    def __init__(self, url: str, name: str, log: Path):
        self.url, self.name, self.log, self.storage = url, name, log, None

    def trials(self) -> list[optuna.trial.FrozenTrial]:
        if self.storage is None:
            if not (self.log.is_file() and "the study so far:" in self.log.read_text()):
                return []
            self.storage = optuna.storages.RDBStorage(self.url)
        return optuna.load_study(study_name=self.name, storage=self.storage).get_trials()


def wait_for(predicate, what: str, procs: dict[str, tuple[subprocess.Popen, Path]], timeout: float = WAIT_S):
    """Wait for ``predicate()``, on progress, failing with the sweeps' output if one of ``procs`` exits first."""
    deadline = time.monotonic() + timeout
    while not predicate():
        for label, (proc, log) in procs.items():
            if proc.poll() is not None:
                raise AssertionError(f"{label} exited {proc.returncode} while waiting for {what}:\n"
                                     f"{log.read_text()[-4000:]}")
        if time.monotonic() > deadline:
            raise AssertionError(f"gave up waiting for {what} after {timeout:.0f} s")
        time.sleep(1.0)


def processes_of(directory: Path) -> list[str]:
    """Command lines of the processes that run something of ``directory`` (a trial's launcher or services)."""
    found = []
    for path in glob.glob("/proc/[0-9]*/cmdline"):
        try:
            cmdline = Path(path).read_bytes().replace(b"\0", b" ").decode(errors="replace")
        except OSError:
            continue
        if str(directory) in cmdline and int(path.split("/")[2]) != os.getpid():
            found.append(cmdline)
    return found


def none_left(directory: Path, timeout: float = 60.0) -> None:
    deadline = time.monotonic() + timeout
    while (left := processes_of(directory)) and time.monotonic() < deadline:
        time.sleep(0.5)
    assert not left, f"processes of the sweep still running: {left}"


def mid_run(trial: optuna.trial.FrozenTrial, directory: Path) -> bool:
    """A running trial whose run has its services live and has not finished (from its launcher's output)."""
    if trial.state != TrialState.RUNNING or "run_name" not in trial.user_attrs:
        return False
    log = directory / "trials" / f"{trial.user_attrs['run_name']}.log"
    text = log.read_text() if log.is_file() else ""
    return "all services live" in text and " finished: " not in text


@pytest.mark.slow
@pytest.mark.timeout(4 * WAIT_S)
def test_a_sweep_of_the_quickstart_prunes_resumes_after_ctrl_c_and_shares_its_study_with_a_second_process(tmp_path):
    sweep_file, directory = tmp_path / "acceptance.toml", tmp_path / "sweep"
    sweep_file.write_text(ACCEPTANCE)
    first_log = tmp_path / "first.log"
    study = Study(f"sqlite:///{directory / 'study.db'}", "acceptance", first_log)
    started = time.monotonic()

    # 1. two trials at once until two have finished and another is mid-run; then Ctrl-C
    first = start_sweep(sweep_file, directory, "--jobs", "2", log=first_log)
    wait_for(lambda: sum(t.state in FINISHED for t in study.trials()) >= 2
             and any(mid_run(t, directory) for t in study.trials()), "2 finished trials and one mid-run",
             {"ebrl sweep": (first, first_log)})
    first.send_signal(signal.SIGINT)
    assert first.wait(300) == 130, first_log.read_text()[-3000:]
    assert "SIGINT received: stopping the trials running here" in first_log.read_text()
    none_left(directory)
    after_ctrl_c = study.trials()
    assert not [t.number for t in after_ctrl_c if t.state == TrialState.RUNNING]
    stopped = [t for t in after_ctrl_c if t.user_attrs.get("failure") == "the sweep was stopped"]
    assert stopped and all(t.state == TrialState.FAIL for t in stopped)
    queued = [t.user_attrs.get("retry_of") for t in after_ctrl_c if t.state == TrialState.WAITING]
    assert sorted(queued) == sorted(t.number for t in stopped)  # their params run again on resume
    for t in stopped:  # stopped as Ctrl-C stops a run: the launcher stopped its services and wrote its summary
        if "run_dir" in t.user_attrs:
            summary = json.loads((Path(t.user_attrs["run_dir"]) / "summary.json").read_text())
            said = (directory / "trials" / f"{t.user_attrs['run_name']}.log").read_text()
            assert "SIGINT received, stopping every service" in said and summary["failure"] is None
            if "all services live" in said:  # (a launcher stopped while its services start exits 1)
                assert summary["exit_code"] == 130
    finished_before = {t.number: (t.state, t.value, t.user_attrs["run_dir"]) for t in after_ctrl_c
                       if t.state in FINISHED}

    # 2. the sweep again, and a second process on the same storage, one trial at a time each
    second_log, resumed_log = tmp_path / "second.log", tmp_path / "resumed.log"
    second = start_sweep(sweep_file, directory, "--jobs", "1", log=second_log)
    procs = {"the second ebrl sweep": (second, second_log)}
    wait_for(lambda: any(t.user_attrs.get("worker", "").endswith(f":{second.pid}") for t in study.trials()),
             "a trial of the second process", procs)
    resumed = start_sweep(sweep_file, directory, "--jobs", "1", log=resumed_log)
    procs["the resumed ebrl sweep"] = (resumed, resumed_log)
    wait_for(lambda: any(t.user_attrs.get("worker", "").endswith(f":{resumed.pid}") for t in study.trials()),
             "a trial of the resumed sweep", procs)
    for label, (proc, log) in procs.items():
        assert proc.wait(WAIT_S) == 0, f"{label}:\n{log.read_text()[-3000:]}"
    none_left(directory)

    trials = study.trials()
    by_number = {t.number: t for t in trials}
    finished = [t for t in trials if t.state in FINISHED]
    assert len(finished) == 8  # n_trials is the study's total, over every run and process
    assert [t for t in trials if t.state == TrialState.PRUNED], "no trial was pruned"
    assert not [t for t in trials if t.state == TrialState.RUNNING]
    for number, before in finished_before.items():  # not run again, not changed
        t = by_number[number]
        assert (t.state, t.value, t.user_attrs["run_dir"]) == before
    later = [t for t in finished if t.number not in finished_before]
    assert len(later) == 8 - len(finished_before)
    workers = {t.user_attrs["worker"].rpartition(":")[2] for t in later}
    assert workers <= {str(second.pid), str(resumed.pid)}
    for pid in (second.pid, resumed.pid):
        assert [t for t in trials if t.user_attrs.get("worker", "").endswith(f":{pid}")], f"no trial of pid {pid}"
    assert not [t for t in trials if t.user_attrs.get("retry_of") in finished_before]
    on_disk = {str(p) for p in (directory / "trials").iterdir() if p.is_dir()}
    recorded = [t.user_attrs["run_dir"] for t in trials if "run_dir" in t.user_attrs]
    assert sorted(on_disk) == sorted(recorded)  # one run per trial, and every run a trial's
    for t in finished:  # each ran with its own params
        cfg = config_mod.load(str(Path(t.user_attrs["run_dir"]) / "config.toml"))
        assert (cfg.train.lr, cfg.algo.clip, cfg.run.iterations) == (t.params["train.lr"], t.params["algo.clip"], 6)

    # 3. the results, and the best config
    rows = list(csv.DictReader(open(directory / "results.csv")))
    assert [int(r["trial"]) for r in rows] == sorted(by_number) and {r["state"] for r in rows} >= {"complete", "pruned"}
    md = (directory / "results.md").read_text()
    assert "| pruned |" in md and "| complete |" in md
    for png in ("history.png", "curves.png"):
        assert (directory / png).stat().st_size > 1000
    complete = sum(t.state == TrialState.COMPLETE for t in trials)
    if complete >= results.IMPORTANCE_MIN:
        assert (directory / "importance.png").stat().st_size > 1000
    else:
        assert f"parameter importance: needs at least 3 complete trials ({complete} so far)" in md
    best = tmp_path / "best.toml"
    out = subprocess.run([sys.executable, "-m", "ebrl.cli", "sweep", str(sweep_file), "--dir", str(directory),
                          "--best", "-o", str(best)], capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    checked = subprocess.run([sys.executable, "-m", "ebrl.cli", "config", str(best)], capture_output=True, text=True,
                             timeout=120, cwd=tmp_path)
    assert checked.returncode == 0, checked.stderr
    top = max((t for t in trials if t.state == TrialState.COMPLETE), key=lambda t: t.value)
    assert config_mod.load(str(best)).train.lr == top.params["train.lr"]
    print(f"sweep test: {time.monotonic() - started:.0f} s; {len(trials)} trials: {complete} complete, "
          f"{sum(t.state == TrialState.PRUNED for t in trials)} pruned, {len(stopped)} stopped by Ctrl-C, "
          f"{sum(t.state == TrialState.FAIL for t in trials)} failed")


@pytest.mark.slow
def test_a_metric_no_run_publishes_fails_its_trial_with_the_reason(tmp_path):
    sweep_file, directory = tmp_path / "typo.toml", tmp_path / "sweep"
    sweep_file.write_text(ACCEPTANCE.replace("n_trials = 8", "n_trials = 3\nmax_failures = 1").replace(
        'metric = "train/episode_return_mean"', 'metric = "train/episode_returns_mean"').replace(
        "iterations = 6", "iterations = 2"))
    log = tmp_path / "typo.log"
    proc = start_sweep(sweep_file, directory, "--jobs", "1", log=log)
    assert proc.wait(WAIT_S) == 1, log.read_text()[-3000:]  # stopped: max_failures trials in a row failed
    (trial,) = Study(f"sqlite:///{directory / 'study.db'}", "acceptance", log).trials()
    assert trial.state == TrialState.FAIL
    assert "objective metric train/episode_returns_mean was never published by train during the run (2 training " \
           "updates) (closest published: train/episode_return_mean" in trial.user_attrs["failure"]
    assert "max_failures" in log.read_text() and "never published" in (directory / "results.md").read_text()


def postgres_binaries() -> Path | None:
    found = sorted(glob.glob("/usr/lib/postgresql/*/bin/pg_ctl")) or [shutil.which("pg_ctl")]
    return Path(found[-1]).parent if found[-1] else None


@pytest.fixture
def postgres_url():
    """A PostgreSQL server of the test's own (initdb and pg_ctl in a temporary directory, as a user other than
    root: PostgreSQL refuses to run as root), on a free loopback port; its URL."""
    bindir = postgres_binaries()
    if bindir is None:
        pytest.skip("PostgreSQL's initdb and pg_ctl are not installed (Debian: apt-get install postgresql)")
    if importlib_util.find_spec("psycopg") is None:
        pytest.skip("no PostgreSQL driver for SQLAlchemy (pip install 'psycopg[binary]': the sweep extra)")
    from ebrl.bus.endpoints import free_port

    data = Path(tempfile.mkdtemp(prefix="ebrl-pg-"))
    as_user: list[str] = []
    if os.geteuid() == 0:
        os.chown(data, pwd.getpwnam("nobody").pw_uid, pwd.getpwnam("nobody").pw_gid)
        as_user = ["runuser", "-u", "nobody", "--"]
    port = free_port()
    try:
        subprocess.run([*as_user, str(bindir / "initdb"), "-D", str(data / "db"), "-U", "ebrl", "--auth=trust"],
                       check=True, capture_output=True, timeout=120)
        subprocess.run([*as_user, str(bindir / "pg_ctl"), "-D", str(data / "db"), "-l", str(data / "server.log"), "-w",
                        "-o", f"-p {port} -k {data} -c listen_addresses=127.0.0.1", "start"],
                       check=True, capture_output=True, timeout=120)
        yield f"postgresql://ebrl@127.0.0.1:{port}/postgres"
    finally:
        subprocess.run([*as_user, str(bindir / "pg_ctl"), "-D", str(data / "db"), "-m", "fast", "stop"],
                       capture_output=True, timeout=120)
        shutil.rmtree(data, ignore_errors=True)


@pytest.mark.slow
@pytest.mark.timeout(2 * WAIT_S)
def test_two_sweep_processes_share_a_study_on_postgresql(tmp_path, postgres_url):
    sweep_file = tmp_path / "pg.toml"
    sweep_file.write_text(ACCEPTANCE.replace("n_trials = 8", "n_trials = 3").replace("iterations = 6",
                                                                                     "iterations = 3"))
    study = Study(postgres_url, "acceptance", tmp_path / "first.log")
    procs = {}
    for label in ("first", "second"):  # each with a directory of its own, as on two machines
        log = tmp_path / f"{label}.log"
        proc = start_sweep(sweep_file, tmp_path / label, "--jobs", "1", "--storage", postgres_url, log=log)
        procs[label] = (proc, log)
        wait_for(lambda: any(t.user_attrs.get("worker", "").endswith(f":{proc.pid}") for t in study.trials()),
                 f"a trial of the {label} process", procs)
    for label, (proc, log) in procs.items():
        assert proc.wait(WAIT_S) == 0, f"{label}:\n{log.read_text()[-3000:]}"
    trials = study.trials()
    assert sum(t.state in FINISHED for t in trials) == 3
    for label, (proc, _) in procs.items():
        mine = [t for t in trials if t.user_attrs.get("worker", "").endswith(f":{proc.pid}")]
        assert mine and all(str(tmp_path / label) in t.user_attrs["run_dir"] for t in mine if "run_dir" in t.user_attrs)
