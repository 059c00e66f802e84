"""The LIBERO evaluation protocol: ``ebrl eval PATH --suite libero_spatial``.

Every task of the suite (or ``--tasks``) runs from its official initial states, the first ``per_task`` of its 50
(all of them by default), in episodes of the suite's step limit after the 10 no-op steps (ebrl/envs/libero.py),
built as the policy was trained (its observation fields, cameras, image size). Episodes run in ``workers``
processes, one env each, a task's episodes dealt out to several when there are fewer tasks than workers.
A task's success rate comes with its Wilson 95 % interval, and the suite's over all its episodes, as published
LIBERO tables report them (the suite's rate is the mean of its tasks' when every task runs as many episodes).
With a camera policy only the observation each action chunk starts from is rendered.
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import json
import math
import multiprocessing
import os
import time
from pathlib import Path
from typing import Any

from ebrl import durable
from ebrl.envs import libero_suite
from ebrl.envs.records import BACKENDS
from ebrl.evaluate import CONFIDENCE, wilson_interval


@dataclasses.dataclass
class TaskResult:
    index: int
    name: str
    language: str
    successes: list[bool]  # one per initial state, in their order
    lengths: list[int]
    init_states: list[int]

    def rate(self) -> tuple[float, float, float]:
        return wilson_interval(sum(self.successes), len(self.successes))


@dataclasses.dataclass
class SuiteResult:
    suite: str
    tasks: list[TaskResult]
    policy: str
    version: int | None
    deterministic: bool
    seconds: float

    def rate(self) -> tuple[float, float, float]:
        flags = [s for t in self.tasks for s in t.successes]
        return wilson_interval(sum(flags), len(flags))

    def table(self) -> str:
        """One row per task (successes, rate, Wilson interval), then the suite's."""
        n = sum(len(t.successes) for t in self.tasks)
        head = (f"{libero_suite.TITLES[self.suite]} ({self.suite}): {self.policy}"
                f"{f' v{self.version}' if self.version is not None else ''}, {len(self.tasks)} tasks, {n} episodes "
                f"from the official initial states, {'deterministic' if self.deterministic else 'stochastic'} "
                f"actions ({self.seconds:.0f} s)")
        lines = [head, "", f"  {'task':>4}  {'instruction':<64} {'success':>8} {'rate':>7}   95 % interval (Wilson)"]
        for t in self.tasks:
            rate, lo, hi = t.rate()
            text = t.language if len(t.language) <= 64 else t.language[:63] + "…"
            lines.append(f"  {t.index:>4}  {text:<64} {f'{sum(t.successes)}/{len(t.successes)}':>8} {rate:>7.1%}"
                         f"   {lo:.1%} .. {hi:.1%}")
        rate, lo, hi = self.rate()
        wins = sum(sum(t.successes) for t in self.tasks)
        lines.append(f"  {'all':>4}  {'':<64} {f'{wins}/{n}':>8} {rate:>7.1%}   {lo:.1%} .. {hi:.1%}")
        return "\n".join(lines)

    def to_json(self) -> dict[str, Any]:
        from ebrl import __version__

        rate, lo, hi = self.rate()
        return {"suite": self.suite, "policy": self.policy, "version": self.version,
                "deterministic": self.deterministic, "confidence": CONFIDENCE, "seconds": self.seconds,
                "success_rate": {"rate": rate, "lo": lo, "hi": hi},
                "tasks": [{"index": t.index, "name": t.name, "instruction": t.language,
                           "success_rate": dict(zip(("rate", "lo", "hi"), t.rate())), "successes": t.successes,
                           "lengths": t.lengths, "init_states": t.init_states} for t in self.tasks],
                "ebrl_version": __version__, "time": time.time()}


def published_row(results: list[SuiteResult]) -> str:
    """The suites side by side, as LIBERO papers tabulate them: success % per suite and their average."""
    names = [libero_suite.TITLES[r.suite] for r in results] + (["Average"] if len(results) > 1 else [])
    values = [f"{100 * r.rate()[0]:.1f} ({100 * r.rate()[1]:.1f}-{100 * r.rate()[2]:.1f})" for r in results]
    if len(results) > 1:
        values.append(f"{100 * sum(r.rate()[0] for r in results) / len(results):.1f}")
    widths = [max(len(a), len(b)) for a, b in zip(names, values)]
    return "\n".join("| " + " | ".join(c.ljust(w) for c, w in zip(row, widths)) + " |"
                     for row in (names, ["-" * w for w in widths], values))


# --- the episodes, in worker processes ------------------------------------------------------------------------

_worker: dict[str, Any] = {}  # in a worker process: its policy and its env of one task


def _init_worker() -> None:
    import torch

    torch.set_num_threads(1)


def _episodes(path: str, which: str, config: str | None, suite: str, task: int, init_states: list[int],
              deterministic: bool) -> tuple[list[bool], list[int]]:
    """Run ``task``'s episodes from ``init_states``; each one's success and length (policy steps)."""
    from ebrl.envs.backends import make_env
    from ebrl.policies.portable import load_policy

    key = (path, which, config)
    if _worker.get("key") != key:
        _worker.clear()
        _worker.update(key=key, policy=load_policy(path, which=which, config=config))
    policy = _worker["policy"]
    if _worker.get("task") != (suite, task):
        if "env" in _worker:
            _worker.pop("env").close()
        kwargs = {**policy.env_spec.kwargs, "tasks": [task], "init_states": True}
        objects = [f.size for f in policy.layout.fields if f.name == "objects"]
        if objects:  # a state policy's object states, padded as in training (a whole suite's pad, not the task's)
            kwargs["object_state_size"] = objects[0]
        spec = dataclasses.replace(policy.env_spec, id=suite, max_episode_steps=0, kwargs=kwargs)  # 0: the suite's
        _worker.update(task=(suite, task), env=make_env(spec))
    env = _worker["env"]
    base, successes, lengths = env.unwrapped, [], []
    for j in init_states:
        obs, _ = env.reset(options={"init_state": j})
        policy.reset(seed=j)
        success, t = False, 0
        while True:
            action, _ = policy.predict(obs, deterministic=deterministic)
            base.skip_observation = (t + 1) % policy.chunk != 0  # the next predict reads the observation only then
            obs, _, terminated, truncated, info = env.step(action)
            t += 1
            success = success or bool(info.get("success"))
            if terminated or truncated:
                break
        base.skip_observation = False
        successes.append(success)
        lengths.append(t)
    return successes, lengths


def evaluate_suite(path: str, suite: str, *, per_task: int = 50, tasks: Any = None, workers: int = 0,
                   deterministic: bool = True, which: str = "latest", config: str | None = None) -> SuiteResult:
    """Run the protocol for ``suite`` (see the module's docstring); ``workers`` 0: one per usable CPU."""
    from ebrl.policies.portable import load_policy

    policy = load_policy(path, which=which, config=config)  # here first: a path without a policy fails at once
    trained_on = policy.env_config.get("backend")
    if not (trained_on in BACKENDS and BACKENDS[trained_on].suites):  # the records of benchmark suites: LIBERO's
        suites = " or ".join(f"{r.label} (env.backend = \"{r.name}\")" for r in BACKENDS.values() if r.suites)
        raise ValueError(f"--suite evaluates a policy trained on {suites}; {policy.path} "
                         f"was trained on {trained_on!r} ({policy.env_config.get('id')!r})")
    chosen = libero_suite.select(suite, tasks)
    count = min(per_task, len(libero_suite.init_states(chosen[0])))
    workers = workers or len(os.sched_getaffinity(0))
    shares = max(1, math.ceil(workers / len(chosen)))  # a task's episodes over several workers when tasks are few
    jobs = [(t.index, list(range(s, count, shares))) for t in chosen for s in range(min(shares, count))]
    start = time.perf_counter()
    ctx = multiprocessing.get_context("spawn")  # fresh interpreters: their own GL choice, no forked threads
    with concurrent.futures.ProcessPoolExecutor(min(workers, len(jobs)), mp_context=ctx,
                                                initializer=_init_worker) as pool:
        futures = [pool.submit(_episodes, str(path), which, config, suite, index, share, deterministic)
                   for index, share in jobs]
        done = [f.result() for f in futures]
    out = []
    for task in chosen:
        runs = sorted((j, s, n) for (index, share), (flags, lengths) in zip(jobs, done) if index == task.index
                      for j, s, n in zip(share, flags, lengths))
        out.append(TaskResult(task.index, task.name, task.language, [s for _, s, _ in runs], [n for _, _, n in runs],
                              [j for j, _, _ in runs]))
    return SuiteResult(suite, out, policy.path, policy.version, deterministic, time.perf_counter() - start)


def command(path: str, suites: list[str], *, episodes: int = 50, tasks: list[int] | None = None, workers: int = 0,
            stochastic: bool = False, best: bool = False, config: str | None = None, out: str | None = None) -> int:
    """``ebrl eval PATH --suite S``: the table of each suite, the published row, ``eval_<suite>.json``; 0, or 2."""
    import sys

    from ebrl.config import ConfigError
    from ebrl.envs import EnvError
    from ebrl.envs.render import RenderingUnavailable

    results = []
    for suite in suites:
        try:
            result = evaluate_suite(path, suite, per_task=episodes, tasks=tasks, workers=workers,
                                    deterministic=not stochastic, which="best" if best else "latest", config=config)
        except (OSError, ValueError, ConfigError, EnvError, RenderingUnavailable, libero_suite.LiberoMissing) as exc:
            print(f"ebrl eval: {exc}", file=sys.stderr)
            return 2
        print(result.table() + "\n")
        directory = Path(path) if Path(path).is_dir() else Path.cwd()
        target = Path(out.format(suite=suite)) if out else directory / f"eval_{suite}.json"
        durable.write_text(target, json.dumps(result.to_json(), indent=1) + "\n")
        print(f"wrote {target}\n")
        results.append(result)
    print(published_row(results))
    return 0
