"""Running a sweep: its Optuna study in the sweep's storage, trials on worker threads of this process, the study's
``n_trials`` shared by every process pointed at the storage, Ctrl-C, and trials that a killed sweep left running.

The budget is a total over the study: a worker starts a trial only while the study's finished trials (complete
or pruned) and running ones fall short of ``n_trials``; one that lost a race with another process for the last
place (both asked at once) is told apart by trial number and given up at once (failed, ``surplus``), so the
study never finishes more than ``n_trials``. Ctrl-C stops every running trial cleanly, fails it and queues its
params again (a new trial, ``retry_of`` its number), as Optuna's heartbeat does with the trials of a sweep that
died: those are failed and queued again once their heartbeat is :data:`GRACE_S` old, or at once where their
sweep ran on this host and its process is gone. Running the sweep again goes on from there.
"""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import sys
import threading
import time
import warnings
from typing import Any, TextIO

import optuna
from optuna.trial import TrialState

from ebrl import config as config_mod
from ebrl.sweep import results, spec
from ebrl.sweep.spec import Sweep, SweepError, core_slots, default_jobs, slug
from ebrl.sweep.trial import Outcome, run_trial

HEARTBEAT_S = 10  # a running trial's heartbeat in the storage
GRACE_S = 60  # a running trial without a heartbeat this long is failed (its sweep died) and queued again
POLL_S = 3.0  # a worker with no trial to start looks again after this long
MAX_RETRIES = 3  # a trial's params are queued again at most this often (a trial that keeps killing its sweep)
FINISHED = (TrialState.COMPLETE, TrialState.PRUNED)
SAMPLERS = {"tpe": "TPESampler", "random": "RandomSampler", "gp": "GPSampler", "cmaes": "CmaEsSampler",
            "qmc": "QMCSampler"}
PRUNERS = {"median": "MedianPruner", "percentile": "PercentilePruner", "hyperband": "HyperbandPruner",
           "successive_halving": "SuccessiveHalvingPruner", "none": "NopPruner"}

warnings.filterwarnings("ignore", category=optuna.exceptions.ExperimentalWarning)
# the heartbeat is recorded here (:class:`Heartbeat`) for trials asked and told one by one, not by Study.optimize
warnings.filterwarnings("ignore", message="Heartbeat of storage is supposed to be used with Study.optimize")


def make_sampler(sweep: Sweep, trials_before: int = 0) -> optuna.samplers.BaseSampler:
    """``[sampler]``: TPE by default, multivariate, a quarter of the trials (2 to 10) sampled at random first, and
    the constant liar so that trials running at once are not sampled alike; other keys to its constructor. A
    ``seed`` is offset by the trials the study held already (``trials_before``): a process that resumes the study,
    or joins it, does not draw the first one's values again."""
    options = dict(sweep.sampler)
    name = options.pop("name")
    if options.get("seed") is not None:
        options["seed"] += trials_before
    if name not in SAMPLERS:
        raise SweepError(f"sampler = {name!r}: one of {', '.join(SAMPLERS)}")
    if name == "tpe":
        options = {"n_startup_trials": max(2, min(10, sweep.n_trials // 4)), "multivariate": True,
                   "constant_liar": True, **options}
    try:
        return getattr(optuna.samplers, SAMPLERS[name])(**options)
    except (TypeError, ValueError, ImportError) as exc:
        raise SweepError(f"sampler {name} ({', '.join(map(str, sweep.sampler.items()))}): {exc}") from None


def make_pruner(sweep: Sweep, cfg: config_mod.Config) -> optuna.pruners.BasePruner:
    """``[pruner]``: the median pruner by default (rl-zoo3's choice), which prunes nothing before a quarter of the
    trials (1 to 5) have completed nor before a third of each trial's training updates; other keys to its
    constructor."""
    options = dict(sweep.pruner)
    name = options.pop("name")
    if name not in PRUNERS:
        raise SweepError(f"pruner = {name!r}: one of {', '.join(PRUNERS)}")
    if name in ("median", "percentile"):
        steps = 0 if sweep.budget.seconds or sweep.budget.env_steps else cfg.run.iterations
        options = {"n_startup_trials": max(1, min(5, sweep.n_trials // 4)),
                   "n_warmup_steps": steps // 3 if steps else 5, **options}
    try:
        return getattr(optuna.pruners, PRUNERS[name])(**options)
    except (TypeError, ValueError) as exc:
        raise SweepError(f"pruner {name} ({', '.join(map(str, sweep.pruner.items()))}): {exc}") from None


def open_storage(url: str) -> optuna.storages.RDBStorage:
    """The study's database (any URL SQLAlchemy takes: ``sqlite:///...``, ``postgresql://...``), with heartbeats:
    the trials of a sweep that died are failed and queued again after :data:`GRACE_S`."""
    kwargs = {"connect_args": {"timeout": 60}} if url.startswith("sqlite") else {"pool_pre_ping": True}
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
            return optuna.storages.RDBStorage(url, engine_kwargs=kwargs, heartbeat_interval=HEARTBEAT_S,
                                              grace_period=GRACE_S, heartbeat_stale_trial_callback=requeue)
    except Exception as exc:  # noqa: BLE001 -- SQLAlchemy's: a bad URL, a missing driver, a refused connection
        raise SweepError(f"storage {url}: {type(exc).__name__}: {exc}") from None


def open_study(sweep: Sweep, cfg: config_mod.Config) -> optuna.Study:
    """The sweep's study, created on first use (the sweep's description kept as its user attribute)."""
    optuna.logging.set_verbosity(optuna.logging.WARNING)  # ebrl sweep says what happens, a line per trial
    storage = open_storage(sweep.storage)
    study = optuna.create_study(storage=storage, study_name=sweep.study, direction=sweep.objective.direction,
                                sampler=make_sampler(sweep), pruner=make_pruner(sweep, cfg), load_if_exists=True)
    study.sampler = make_sampler(sweep, len(study.get_trials(deepcopy=False)))
    if study.direction.name.lower() != sweep.objective.direction:
        raise SweepError(f"study {sweep.study} in {sweep.storage} was made to {study.direction.name.lower()}; this "
                         f"sweep would {sweep.objective.direction} (give it another study name)")
    if "sweep" not in study.user_attrs:
        study.set_user_attr("sweep", {"config": sweep.config, "objective": sweep.objective.describe(),
                                      "params": {p.key: p.describe() for p in sweep.params}, "set": sweep.overrides()})
    return study


def requeue(study: optuna.Study, trial: optuna.trial.FrozenTrial) -> None:
    """Queue a stopped trial's params again (a new trial, ``retry_of`` the first of them), at most
    :data:`MAX_RETRIES` times."""
    first = trial.user_attrs.get("retry_of", trial.number)
    if sum(t.user_attrs.get("retry_of") == first for t in study.get_trials(deepcopy=False)) < MAX_RETRIES:
        study.enqueue_trial(trial.params, user_attrs={"retry_of": first})


def counts(trials: list[optuna.trial.FrozenTrial]) -> tuple[int, int]:
    """(finished: complete or pruned, running) among ``trials``."""
    return sum(t.state in FINISHED for t in trials), sum(t.state == TrialState.RUNNING for t in trials)


def surplus(trials: list[optuna.trial.FrozenTrial], number: int, n_trials: int) -> bool:
    """Whether trial ``number``, just started, is one too many: the finished trials and those running that started
    before it (lower numbers) fill ``n_trials`` already."""
    finished, _ = counts(trials)
    ahead = sum(t.state == TrialState.RUNNING and t.number < number for t in trials)
    return finished + ahead >= n_trials


def gone_here(trials: list[optuna.trial.FrozenTrial], host: str, pid: int, mine: set[int]) -> list[Any]:
    """Running trials whose sweep ran on this host and is gone: its process has exited (or it is this process,
    which does not run them)."""
    out = []
    for t in trials:
        where, _, owner = str(t.user_attrs.get("worker", "")).rpartition(":")
        if t.state != TrialState.RUNNING or where != host or not owner.isdigit():
            continue
        if int(owner) == pid:
            if t.number not in mine:
                out.append(t)
            continue
        try:
            os.kill(int(owner), 0)
        except ProcessLookupError:
            out.append(t)
        except PermissionError:  # another user's process: alive
            pass
    return out


class Heartbeat:
    """Records a running trial's heartbeat in the storage every :data:`HEARTBEAT_S` from a thread of its own."""

    def __init__(self, storage: Any, trial_id: int):
        self.storage, self.trial_id, self.done = storage, trial_id, threading.Event()
        self.thread = threading.Thread(target=self._beat, name=f"heartbeat {trial_id}", daemon=True)

    def __enter__(self) -> "Heartbeat":
        self.thread.start()
        return self

    def __exit__(self, *exc: Any) -> None:
        self.done.set()
        self.thread.join()

    def _beat(self) -> None:
        while True:
            with contextlib.suppress(Exception):  # a busy database: the next beat
                self.storage.record_heartbeat(self.trial_id)
            if self.done.wait(HEARTBEAT_S):
                return


class Sweeper:
    """This process's part of a sweep: ``jobs`` worker threads, each running one trial at a time, until the study
    has ``n_trials`` finished trials, Ctrl-C, or ``max_failures`` failed trials in a row."""

    def __init__(self, sweep: Sweep, study: optuna.Study, out: TextIO = sys.stdout):
        self.sweep, self.study, self.out = sweep, study, out
        self.jobs = sweep.jobs or default_jobs(sweep.cores_per_trial)
        self.stopping = threading.Event()
        self.lock = threading.Lock()  # asking for a trial, the failure count, printing, the results table
        self.mine: set[int] = set()  # numbers of the trials this process runs now
        self.worker = f"{socket.gethostname()}:{os.getpid()}"
        self.failed_in_a_row = 0
        self.code = 0
        self.waiting_said = False

    def say(self, line: str) -> None:
        with self.lock:
            print(line, file=self.out, flush=True)

    def run(self) -> int:
        """Run trials until the study is done or the sweep stops; write the results. The exit code: 0 (the study
        has its trials), 1 (too many failures), 130/143 (SIGINT/SIGTERM)."""
        slots = core_slots(self.jobs, self.sweep.cores_per_trial)
        threads = [threading.Thread(target=self.work, args=(cores,), name=f"sweep slot {i}")
                   for i, cores in enumerate(slots)]
        previous = {sig: signal.signal(sig, self.on_signal) for sig in (signal.SIGINT, signal.SIGTERM)}
        try:
            for thread in threads:
                thread.start()
            while any(thread.is_alive() for thread in threads):
                for thread in threads:
                    thread.join(0.5)
        finally:
            for sig, handler in previous.items():
                signal.signal(sig, handler)
        for line in results.write_all(self.study, self.sweep):
            self.say(line)
        return self.code

    def on_signal(self, sig: int, frame: Any) -> None:
        if self.stopping.is_set():
            self.say("ebrl sweep: stopping already (each trial's run gets SIGTERM, then SIGKILL, if it does not end)")
            return
        self.code = 128 + sig
        self.say(f"\nebrl sweep: {signal.Signals(sig).name} received: stopping the trials running here (they are "
                 "queued again); run the sweep again to go on")
        self.stopping.set()

    def work(self, cores: list[int] | None) -> None:
        """One slot: trials one after another. An error of the storage (a database that stays locked or out of
        reach) stops the sweep, saying so; a trial it left running is failed and queued again later."""
        while not self.stopping.is_set():
            trial = None
            try:
                trial = self.next_trial()
                if trial is None:
                    return
                self.run_one(trial, cores)
            except Exception as exc:  # noqa: BLE001 -- SQLAlchemy's, from the storage
                self.say(f"ebrl sweep: {type(exc).__name__}: {exc}; stopping")
                self.code = self.code or 1
                self.stopping.set()
            finally:
                if trial is not None:
                    with self.lock:
                        self.mine.discard(trial.number)

    def next_trial(self) -> optuna.Trial | None:
        """A new trial of the study where its budget has room (None once it is done, or the sweep is stopping);
        while the trials running elsewhere fill it, wait: one may fail and need running again."""
        n = self.sweep.n_trials
        while not self.stopping.is_set():
            self.reap()
            with self.lock:
                finished, running = counts(self.study.get_trials(deepcopy=False))
                if finished >= n:
                    return None
                if finished + running < n:
                    trial = self.study.ask()
                    trial.set_user_attr("worker", self.worker)
                    if not surplus(self.study.get_trials(deepcopy=False), trial.number, n):
                        self.mine.add(trial.number)
                        return trial
                    trial.set_user_attr("failure", "surplus: the study's n_trials were taken by other workers")
                    self.study.tell(trial, state=TrialState.FAIL)
                elif not self.waiting_said:
                    self.waiting_said = True
                    print(f"waiting: {running} trials running elsewhere fill the study's {n} (finished: {finished})",
                          file=self.out, flush=True)
            self.stopping.wait(POLL_S)
        return None

    def reap(self) -> None:
        """Fail, and queue again, the running trials whose sweep is gone: heartbeat too old, or its process on this
        host has exited."""
        optuna.storages.fail_stale_trials(self.study)
        host, _, pid = self.worker.rpartition(":")
        with self.lock:
            gone = gone_here(self.study.get_trials(deepcopy=False), host, int(pid), self.mine)
        for trial in gone:
            with contextlib.suppress(Exception):  # another process failed it first
                self.study._storage.set_trial_user_attr(trial._trial_id, "failure",
                                                        f"its sweep ({trial.user_attrs['worker']}) is gone")
                self.study.tell(trial.number, state=TrialState.FAIL)
                requeue(self.study, trial)
                self.say(f"trial {trial.number}: its sweep ({trial.user_attrs['worker']}) is gone: failed, queued again")

    def run_one(self, trial: optuna.Trial, cores: list[int] | None) -> None:
        sweep = self.sweep
        values = {p.key: p.suggest(trial) for p in sweep.params}
        name = f"{slug(sweep.study)[:40]}-t{trial.number:04d}"
        trial.set_user_attr("run_name", name)
        self.say(f"trial {trial.number} started: {results.format_params(values)}" + (
            f" (retry of trial {trial.user_attrs['retry_of']})" if "retry_of" in trial.user_attrs else ""))
        started = time.monotonic()
        with Heartbeat(self.study._storage, trial._trial_id):
            outcome = run_trial(trial, sweep.config, sweep.trial_overrides(name, values), name,
                                sweep.directory / "trials", sweep.objective, sweep.budget, self.stopping, cores)
        trial.set_user_attr("seconds", round(time.monotonic() - started, 1))
        if outcome.run_dir is not None:
            trial.set_user_attr("run_dir", str(outcome.run_dir))
        self.finish(trial, outcome)

    def finish(self, trial: optuna.Trial, outcome: Outcome) -> None:
        """Tell the study how the trial ended, say it, and update the results table."""
        number = trial.number
        if outcome.reason:
            trial.set_user_attr("note" if outcome.state in ("complete", "pruned") else "failure", outcome.reason)
        try:
            if outcome.state == "complete":
                self.study.tell(trial, outcome.value)
            elif outcome.state == "pruned":
                self.study.tell(trial, state=TrialState.PRUNED)
            else:
                self.study.tell(trial, state=TrialState.FAIL)
                if outcome.state == "interrupted":
                    requeue(self.study, self.study._storage.get_trial(trial._trial_id))
        except (optuna.exceptions.UpdateFinishedTrialError, ValueError, RuntimeError) as exc:
            self.say(f"trial {number}: could not be told to the study ({exc}); another process failed it")
        self.say(results.trial_line(number, outcome, self.sweep, self.study))
        with self.lock:
            self.failed_in_a_row = self.failed_in_a_row + 1 if outcome.state == "failed" else 0
            if self.failed_in_a_row >= self.sweep.max_failures and not self.stopping.is_set():
                self.code = 1
                print(f"ebrl sweep: {self.failed_in_a_row} trials in a row failed (max_failures); stopping. The last: "
                      f"{outcome.reason}", file=self.out, flush=True)
                self.stopping.set()
            results.write_table(self.study, self.sweep)


def command(target: str, *, params: list[str], sets: list[str], best: bool = False, output: str | None = None,
            report: bool = False, out: TextIO = sys.stdout, **given: Any) -> int:
    """``ebrl sweep``: run the sweep (``best``: print its best config instead, or write it to ``output``;
    ``report``: write the results table and plots only). Exit 2 where it cannot run, naming why."""
    try:
        sweep = spec.load(target, params=params, sets=sets, **given)
        cfg = spec.check(sweep)
        sweep.directory.mkdir(parents=True, exist_ok=True)
        study = open_study(sweep, cfg)
        if best:
            text = results.best_config(study, sweep)
            if output:
                with open(output, "w") as fh:
                    fh.write(text)
                print(f"{output}: the best trial's config; check it with `ebrl config {output}`, run it with "
                      f"`ebrl up {output}`", file=out)
            else:
                print(text, end="", file=out)
            return 0
    except (SweepError, OSError) as exc:
        print(f"ebrl sweep: {exc}", file=sys.stderr)
        return 2
    if report:
        for line in results.write_all(study, sweep):
            print(line, file=out)
        return 0
    sweeper = Sweeper(sweep, study, out)
    print(results.header(sweep, study, sweeper.jobs), file=out, flush=True)
    return sweeper.run()
