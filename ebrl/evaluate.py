"""Evaluating a policy: episodes in plain gymnasium loops, confidence intervals, videos, ``eval.json``.

Used by ``ebrl eval PATH`` and by the eval service (``ebrl/services/eval.py``), the same code for both:

- :func:`run_episodes` plays episodes of the policy's own environment (built as training built it,
  ``ebrl.envs``) on the CPU, one after another; episode i resets with seed ``seed + i``, so an evaluation is
  reproducible and every version is scored on the same initial states. The default first seed,
  :data:`EVAL_SEED`, is far from training's reset seeds (``run.seed * 100003 + env + 7919 * episode``):
  evaluation runs on held-out episodes. A success is ``info["success"]`` at any step of the episode (what
  training counts in ``sim/success_rate``); an env without it has no success rate.
- :func:`t_interval` (the return: mean ± Student-t 95 % interval) and :func:`wilson_interval` (the success rate:
  Wilson score 95 % interval, sound at 0 % and 100 % and for few episodes).
- Videos of the first episodes (``env.render()`` as RGB frames): MP4 (H.264) through imageio-ffmpeg when it is
  installed (a dependency of EBRL), else an animated GIF.
- :class:`EvalPool`: the eval service's episodes in worker processes on its own cores at idle priority.
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
from typing import Any, Callable

import numpy as np

from ebrl import durable

EVAL_SEED = 2_000_000_000  # the first evaluation episode's reset seed (eval.seeds, ebrl eval --seed)
MAX_EPISODE_STEPS = 100_000  # an episode still running after this many steps is cut (an env without a time limit)
CONFIDENCE = 0.95
EVAL_FILE = "eval.json"


# --- confidence intervals -----------------------------------------------------------------------------


def t_interval(values: Any, confidence: float = CONFIDENCE) -> tuple[float, float, float]:
    """(mean, low, high): the mean and its Student-t interval; low = high = nan with fewer than 2 values."""
    from scipy import stats

    x = np.asarray(values, dtype=np.float64)
    mean = float(x.mean()) if len(x) else math.nan
    if len(x) < 2:
        return mean, math.nan, math.nan
    if (sem := float(stats.sem(x))) == 0:  # every value the same: no spread (scipy would say nan)
        return mean, mean, mean
    lo, hi = stats.t.interval(confidence, len(x) - 1, loc=mean, scale=sem)
    return mean, float(lo), float(hi)


def wilson_interval(successes: int, n: int, confidence: float = CONFIDENCE) -> tuple[float, float, float]:
    """(rate, low, high): the success rate and its Wilson score interval (nan for n = 0)."""
    from scipy import stats

    if n <= 0:
        return math.nan, math.nan, math.nan
    ci = stats.binomtest(successes, n).proportion_ci(confidence_level=confidence, method="wilson")
    lo = 0.0 if successes == 0 else max(0.0, float(ci.low))  # exact at the ends (rounding leaves 1 - 1e-16)
    hi = 1.0 if successes == n else min(1.0, float(ci.high))
    return successes / n, lo, hi


# --- results ------------------------------------------------------------------------------------------


@dataclasses.dataclass
class Episode:
    seed: int
    ret: float
    length: int
    success: bool | None  # None: the env reports no success
    video: str | None = None


@dataclasses.dataclass
class EvalResult:
    """The episodes of one evaluation and what is reported of them."""

    episodes: list[Episode]
    deterministic: bool
    version: int | None = None
    policy: str = ""
    env_id: str = ""
    seconds: float = 0.0

    @property
    def returns(self) -> np.ndarray:
        return np.array([e.ret for e in self.episodes], np.float64)

    @property
    def successes(self) -> list[bool] | None:
        """Each episode's success, or None when the env reports none."""
        flags = [e.success for e in self.episodes]
        return None if any(f is None for f in flags) or not flags else [bool(f) for f in flags]

    def summary(self) -> dict[str, Any]:
        mean, lo, hi = t_interval(self.returns)
        lengths = [e.length for e in self.episodes]
        out: dict[str, Any] = {
            "return": {"mean": mean, "lo": _finite(lo), "hi": _finite(hi),
                       "std": float(self.returns.std(ddof=1)) if len(self.returns) > 1 else None},
            "success_rate": None,
            "episode_length": {"mean": float(np.mean(lengths)), "min": int(min(lengths)), "max": int(max(lengths))},
        }
        if (flags := self.successes) is not None:
            rate, s_lo, s_hi = wilson_interval(sum(flags), len(flags))
            out["success_rate"] = {"rate": rate, "lo": s_lo, "hi": s_hi, "successes": sum(flags)}
        return out

    def metrics(self) -> dict[str, float]:
        """The eval service's stats report: ``eval/return`` (with ``_lo``/``_hi``), ``eval/success_rate`` (with
        ``_lo``/``_hi``; absent when the env reports no success), ``eval/episode_length``, ``eval/version``."""
        s = self.summary()
        out = {"eval/return": s["return"]["mean"], "eval/episode_length": s["episode_length"]["mean"],
               "eval/episodes": float(len(self.episodes)), "eval/eval_s": self.seconds}
        if s["return"]["lo"] is not None:
            out["eval/return_lo"], out["eval/return_hi"] = s["return"]["lo"], s["return"]["hi"]
        if s["success_rate"] is not None:
            rate = s["success_rate"]
            out.update({"eval/success_rate": rate["rate"], "eval/success_rate_lo": rate["lo"],
                        "eval/success_rate_hi": rate["hi"]})
        if self.version is not None:
            out["eval/version"] = float(self.version)
        return out

    def to_json(self) -> dict[str, Any]:
        """What ``eval.json`` holds."""
        from ebrl import __version__

        return {"policy": self.policy, "version": self.version, "env": self.env_id,
                "episodes": len(self.episodes), "seeds": [e.seed for e in self.episodes],
                "deterministic": self.deterministic, "confidence": CONFIDENCE, **self.summary(),
                "per_episode": [{"seed": e.seed, "return": e.ret, "length": e.length, "success": e.success,
                                 "video": e.video} for e in self.episodes],
                "videos": [e.video for e in self.episodes if e.video], "seconds": self.seconds,
                "ebrl_version": __version__, "time": time.time()}

    def table(self) -> str:
        """The printed summary: return, success rate, episode length, with their intervals."""
        s = self.summary()
        n, ret = len(self.episodes), s["return"]
        lines = [f"{self.env_id or 'policy'}{f' v{self.version}' if self.version is not None else ''}: {n} episodes, "
                 f"{'deterministic' if self.deterministic else 'stochastic'} actions, seeds "
                 f"{self.episodes[0].seed}..{self.episodes[-1].seed} ({self.seconds:.1f} s)",
                 "",
                 f"  {'':<16} {'value':>10}   {'95 % interval':<22}",
                 f"  {'return':<16} {ret['mean']:>10.2f}   " + (
                     f"{ret['lo']:.2f} .. {ret['hi']:.2f} (t, ±{(ret['hi'] - ret['lo']) / 2:.2f})"
                     if ret["lo"] is not None else "-")]
        if s["success_rate"] is not None:
            rate = s["success_rate"]
            lines.append(f"  {'success rate':<16} {rate['rate']:>10.1%}   {rate['lo']:.1%} .. {rate['hi']:.1%} "
                         f"(Wilson; {rate['successes']}/{n})")
        else:
            lines.append(f"  {'success rate':<16} {'-':>10}   (the env reports no success)")
        length = s["episode_length"]
        lines.append(f"  {'episode length':<16} {length['mean']:>10.1f}   min {length['min']}, max {length['max']}")
        return "\n".join(lines)


def _finite(x: float) -> float | None:
    return x if math.isfinite(x) else None


def write_json(result: EvalResult, path: str | os.PathLike) -> Path:
    """``result`` as JSON at ``path``, written durably and atomically (``ebrl.durable``)."""
    return durable.write_text(path, json.dumps(result.to_json(), indent=1) + "\n")


# --- videos ---------------------------------------------------------------------------------------------


def video_format() -> str:
    """``mp4`` when an ffmpeg encoder is installed (imageio-ffmpeg), else ``gif``."""
    try:
        import imageio_ffmpeg

        imageio_ffmpeg.get_ffmpeg_exe()
        return "mp4"
    except (ImportError, RuntimeError):
        return "gif"


class VideoWriter:
    """Frames to ``<stem>.mp4`` (or ``.gif`` where no encoder is installed) at ``fps``, as they come. The file is
    written as ``<stem>.tmp.<format>`` and renamed when it is complete: an episode cut short (the run ended, the
    service was stopped) leaves no truncated video under the final name."""

    def __init__(self, stem: str | os.PathLike, fps: float, fmt: str | None = None):
        import imageio

        self.format = fmt or video_format()
        self.path = Path(f"{stem}.{self.format}")
        self._tmp = Path(f"{stem}.tmp.{self.format}")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        if self.format == "mp4":  # yuv420p plays everywhere; frame sides are rounded up to a multiple of 16
            self._writer = imageio.get_writer(self._tmp, fps=fps, codec="libx264", quality=7,
                                              pixelformat="yuv420p", ffmpeg_log_level="error")
        else:
            self._writer = imageio.get_writer(self._tmp, duration=1000.0 / fps, loop=0)
        self.frames = 0

    def add(self, frame: np.ndarray | None) -> None:
        if frame is not None:
            self._writer.append_data(np.asarray(frame, np.uint8))
            self.frames += 1

    def close(self) -> None:
        """Finish the file and give it its name."""
        self._writer.close()
        os.replace(self._tmp, self.path)

    def abort(self) -> None:
        """Drop the unfinished file."""
        try:
            self._writer.close()
        finally:
            self._tmp.unlink(missing_ok=True)


def env_fps(env: Any) -> float:
    metadata = getattr(env, "metadata", None) or getattr(env.unwrapped, "metadata", {}) or {}
    fps = metadata.get("render_fps") or getattr(env.unwrapped, "control_freq", None)
    return float(fps) if fps else 30.0


# --- episodes ---------------------------------------------------------------------------------------------


def run_episodes(policy: Any, episodes: int, seed: int = EVAL_SEED, deterministic: bool = True, *,
                 video_dir: str | os.PathLike | None = None, video_episodes: int = 0,
                 indices: list[int] | None = None, env: Any = None,
                 on_episode: Callable[[Episode], None] | None = None) -> EvalResult:
    """Play episodes of ``policy`` (an ``ebrl.load_policy`` result) in its environment, in a plain gymnasium loop.

    Episode i (``indices``, default ``range(episodes)``) resets the env with seed ``seed + i`` and the policy
    (its chunk, and its sampling generator) with the same seed. The first ``video_episodes`` episodes are
    recorded to ``video_dir/episode-<i>.mp4`` (or ``.gif``). ``env``: one to reuse (built with
    ``render_mode="rgb_array"`` when videos are wanted); default: built here and closed after."""
    indices = list(range(episodes)) if indices is None else list(indices)
    video = video_dir is not None and video_episodes > 0 and any(i < video_episodes for i in indices)
    own = env is None
    if own:
        env = policy.make_env(render_mode="rgb_array" if video else None)
    start = time.perf_counter()
    out = []
    try:
        for i in indices:
            recorder = (VideoWriter(Path(video_dir) / f"episode-{i}", env_fps(env))
                        if video and i < video_episodes else None)
            episode = _episode(policy, env, seed + i, deterministic, recorder)
            out.append(episode)
            if on_episode is not None:
                on_episode(episode)
    finally:
        if own:
            env.close()
    return EvalResult(out, deterministic, version=policy.version, policy=policy.path,
                      env_id=policy.env_config.get("id", ""), seconds=time.perf_counter() - start)


def _episode(policy: Any, env: Any, seed: int, deterministic: bool, recorder: VideoWriter | None) -> Episode:
    obs, _ = env.reset(seed=seed)
    policy.reset(seed=seed)
    total, length, success = 0.0, 0, None
    try:
        if recorder is not None:
            recorder.add(env.render())
        while length < MAX_EPISODE_STEPS:
            obs, reward, terminated, truncated, info = env.step(policy.predict(obs, deterministic=deterministic)[0])
            total += float(reward)
            length += 1
            if "success" in info:
                success = bool(success) or bool(info["success"])
            if recorder is not None:
                recorder.add(env.render())
            if terminated or truncated:
                break
    except BaseException:
        if recorder is not None:
            recorder.abort()
        raise
    if recorder is not None:
        recorder.close()
    return Episode(seed, total, length, success, str(recorder.path) if recorder is not None else None)


# --- ebrl eval ---------------------------------------------------------------------------------------------


def command(path: str, *, episodes: int = 10, seed: int | None = None, video: str | None = None,
            video_episodes: int = 3, stochastic: bool = False, best: bool = False, config: str | None = None,
            out: str | None = None) -> int:
    """``ebrl eval PATH``: evaluate, print the table, write ``eval.json``; 0, or 2 when nothing could be run."""
    import sys

    from ebrl.config import ConfigError
    from ebrl.envs import EnvError
    from ebrl.envs.render import RenderingUnavailable, choose_gl
    from ebrl.policies.portable import load_policy

    if episodes < 1 or video_episodes < 0:
        print("ebrl eval: --episodes must be >= 1 and --video-episodes >= 0", file=sys.stderr)
        return 2
    try:
        if video:
            choose_gl()  # MuJoCo renders offscreen: its GL backend is fixed when mujoco is first imported
        policy = load_policy(path, which="best" if best else "latest", config=config)
        result = run_episodes(policy, episodes, EVAL_SEED if seed is None else seed, not stochastic,
                              video_dir=video, video_episodes=video_episodes if video else 0)
    except (OSError, ValueError, ConfigError, EnvError, RenderingUnavailable) as exc:
        print(f"ebrl eval: {exc}", file=sys.stderr)
        return 2
    print(result.table())
    target = Path(out) if out else (Path(path) / EVAL_FILE if Path(path).is_dir() else Path.cwd() / EVAL_FILE)
    print(f"policy: {policy.path}")
    for episode in result.episodes:
        if episode.video:
            print(f"video: {episode.video}")
    print(f"wrote {write_json(result, target)}")
    return 0


# --- the eval service: which versions, the best one, the workers ---------------------------------------------


class EvalSchedule:
    """Which weights versions the eval service evaluates: ``every``-th ones (v > 0) and ``final`` (run.iterations,
    0: none). One due version waits while an evaluation runs; a newer due one replaces it (``skipped``), so a
    slow evaluation falls behind by dropping versions, never by queueing them, and always takes the newest."""

    def __init__(self, every: int, final: int = 0):
        self.every, self.final = every, final
        self.pending: Any = None  # the weights waiting (anything with a .version)
        self.last = -1  # the newest version taken for evaluation
        self.skipped = 0

    def due(self, version: int) -> bool:
        return version > max(self.last, 0) and (version % self.every == 0 or version == self.final)

    def offer(self, weights: Any) -> bool:
        """A new version arrived; True if it is now the one waiting."""
        if not self.due(weights.version) or (self.pending is not None and weights.version <= self.pending.version):
            return False
        if self.pending is not None:
            self.skipped += 1
        self.pending = weights
        return True

    def take(self) -> Any:
        """The weights to evaluate next (None: none waiting)."""
        weights, self.pending = self.pending, None
        if weights is not None:
            self.last = weights.version
        return weights


def score(result: EvalResult) -> tuple[float, float]:
    """How evaluations rank: success rate (an env without one: all equal), then mean return."""
    summary = result.summary()
    rate = summary["success_rate"]["rate"] if summary["success_rate"] is not None else -1.0
    return rate, summary["return"]["mean"]


class BestPolicy:
    """``RUN_DIR/best.safetensors``: the evaluated version with the best :func:`score`, a portable policy whose
    metadata also holds its evaluation (``eval_success_rate``, ``eval_return``, ...). A restarted eval service
    (or a resumed run) reads the score of the file already there and only replaces it with a better one."""

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        self.score: tuple[float, float] | None = None
        self.version: int | None = None
        if self.path.is_file():
            from ebrl.policies.checkpoint import read_metadata

            try:
                meta = read_metadata(str(self.path))
                self.score = (float(meta["eval_success_rate"]), float(meta["eval_return"]))
                self.version = int(meta["version"])
            except (KeyError, ValueError, OSError):
                self.score = None  # unreadable: the next evaluation replaces it

    def better(self, result: EvalResult) -> bool:
        return self.score is None or score(result) > self.score

    def save(self, model: Any, metadata: dict[str, str], result: EvalResult) -> Path:
        """Write ``model`` (holding ``result``'s weights) atomically (fsynced) as the best policy."""
        from ebrl.policies import save_checkpoint

        rate, ret = score(result)
        save_checkpoint(model, str(self.path), {
            **metadata, "version": str(result.version), "eval_success_rate": repr(rate), "eval_return": repr(ret),
            "eval_episodes": str(len(result.episodes)), "eval_first_seed": str(result.episodes[0].seed),
            "eval_deterministic": str(result.deterministic).lower()})
        self.score, self.version = (rate, ret), result.version
        return self.path


# --- the eval service's workers -----------------------------------------------------------------------------


class EvalPool:
    """Evaluations in ``len(cores)`` worker processes (one when ``cores`` is empty), each pinned to its core
    (any core when empty) at idle priority (``SCHED_IDLE``: it runs only when nothing else wants the core),
    with one torch thread. The episodes of an evaluation are dealt out round-robin; each worker builds the
    policy from ``metadata`` once and loads each version's weights into it, and keeps its env."""

    def __init__(self, metadata: dict[str, str], cores: list[int] | None = None, render: bool = False):
        """``render``: some evaluations record videos (a MuJoCo env's GL backend is then chosen as each worker
        starts, before anything imports mujoco there)."""
        self.metadata, self.cores = metadata, list(cores or [])
        self.workers = max(1, len(self.cores))
        ctx = multiprocessing.get_context("spawn")  # a fresh interpreter: no forked threads, its own GL choice
        queue = ctx.Queue()
        for core in self.cores:
            queue.put(core)
        self._pool = concurrent.futures.ProcessPoolExecutor(self.workers, mp_context=ctx, initializer=_init_worker,
                                                            initargs=(queue, bool(self.cores), render))

    def evaluate(self, params: dict[str, np.ndarray], version: int, episodes: int, seed: int, deterministic: bool,
                 video_dir: str | None = None, video_episodes: int = 0) -> EvalResult:
        """One evaluation of the weights ``params`` as ``version`` (blocks; call it off the event loop)."""
        start = time.perf_counter()
        futures = [self._pool.submit(_evaluate_share, self.metadata, params, list(range(w, episodes, self.workers)),
                                     seed, deterministic, video_dir, video_episodes)
                   for w in range(min(self.workers, episodes))]
        done = sorted((e for f in futures for e in f.result()), key=lambda e: e.seed)
        return EvalResult(done, deterministic, version=version, policy="", env_id=json.loads(
            self.metadata["env"]).get("id", ""), seconds=time.perf_counter() - start)

    def close(self) -> None:
        """Stop at once: the workers are killed (an evaluation in progress is dropped, its video never named)."""
        processes = list((getattr(self._pool, "_processes", None) or {}).values())  # CPython's; no public API
        self._pool.shutdown(wait=False, cancel_futures=True)
        for process in processes:
            process.kill()


_worker: dict[str, Any] = {}  # in a worker process: its policy, env and the metadata they were built from


def _init_worker(cores: Any, pinned: bool, render: bool) -> None:
    import ctypes
    import signal

    import torch

    if render:
        from ebrl.envs.render import choose_gl

        choose_gl()
    ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG: dies with the service
    lower_priority()
    if pinned:
        os.sched_setaffinity(0, {cores.get(timeout=10)})
    torch.set_num_threads(1)


def lower_priority() -> str:
    """This process (and what it starts) at idle priority: ``SCHED_IDLE`` where allowed, else nice 19."""
    try:
        os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
        return "SCHED_IDLE"
    except (AttributeError, OSError):
        os.nice(19 - os.nice(0))
        return "nice 19"


def _evaluate_share(metadata: dict[str, str], params: dict[str, np.ndarray], indices: list[int], seed: int,
                    deterministic: bool, video_dir: str | None, video_episodes: int) -> list[Episode]:
    from ebrl.policies import load_arrays
    from ebrl.policies.portable import from_metadata

    if _worker.get("metadata") != metadata:
        for key in ("env", "env_video"):
            if key in _worker:
                _worker[key].close()
        _worker.clear()
        _worker.update(metadata=metadata, policy=from_metadata(metadata))
    policy = _worker["policy"]
    load_arrays(policy.model, params, source="eval weights")
    video = video_dir is not None and any(i < video_episodes for i in indices)
    key = "env_video" if video else "env"
    if key not in _worker:
        _worker[key] = policy.make_env(render_mode="rgb_array" if video else None)
    result = run_episodes(policy, 0, seed, deterministic, video_dir=video_dir, video_episodes=video_episodes,
                          indices=indices, env=_worker[key])
    return result.episodes
