"""Env worker: one environment in its own process, driven from the event loop over a pipe.

One process per environment so that each can be pinned to a core. A request
is one pickled tuple; the parent awaits the reply through ``loop.add_reader``
on the pipe, so hundreds of workers need no threads. Workers never outlive the
sim service, even in the middle of a step: one exits when its pipe closes, is
SIGKILLed when its parent process dies (``PR_SET_PDEATHSIG``), and, since that
parent is the forkserver (which lives on while any worker does), when the sim
service exits (a thread waiting on a pidfd of it).
"""

from __future__ import annotations

import asyncio
import ctypes
import multiprocessing as mp
import multiprocessing.context
import multiprocessing.popen_forkserver
import multiprocessing.spawn
import os
import select
import signal
import threading
import time
from dataclasses import dataclass, field
from multiprocessing.connection import Connection
from typing import Any, Callable, Iterable

import numpy as np

import ebrl.envs.guard as guard
from ebrl.envs.backends import backend, lazy_observer, make_env
from ebrl.envs.render import ensure_gl_for
from ebrl.envs.spec import EnvSpec
from ebrl.resources.corepool import CoreClaim, CorePool, ParentGone, pin_threads

_CTX = None
EPISODE_SEED_STRIDE = 7919  # episode k of a worker seeded s starts from reset(seed=s + EPISODE_SEED_STRIDE * k)
PR_SET_PDEATHSIG = 1  # prctl(2)
# The forkserver preloads this module, so there this is its pid: the parent of every worker it forks.
_IMPORTED_BY = os.getpid()


class _Launching(threading.local):
    bare = False  # this thread is starting a worker: its preparation leaves the parent's main module out


_LAUNCHING = _Launching()
_preparation_data = mp.spawn.get_preparation_data


def _worker_preparation_data(name: str) -> dict[str, Any]:
    """multiprocessing's preparation of a child, without the parent's ``__main__`` for a worker: a child of the
    forkserver imports the parent's main module first (``ebrl.services.sim``, ``ebrl.process`` and all they
    import), which took 3.3 of the 3.8 s eight quickstart workers needed to answer their first reset. A worker
    runs functions of ``ebrl.envs`` alone, which the forkserver has imported."""
    data = _preparation_data(name)
    if _LAUNCHING.bare:
        data.pop("init_main_from_name", None)
        data.pop("init_main_from_path", None)
    return data


mp.spawn.get_preparation_data = _worker_preparation_data  # what it returns changes only for _BarePopen


class _BarePopen(mp.popen_forkserver.Popen):
    def _launch(self, process_obj: Any) -> None:
        _LAUNCHING.bare = True
        try:
            super()._launch(process_obj)
        finally:
            _LAUNCHING.bare = False


class BareProcess(mp.context.ForkServerProcess):
    """A process of the forkserver that does not import the parent's main module (:func:`_worker_preparation_data`)."""

    @staticmethod
    def _Popen(process_obj: Any) -> Any:
        return _BarePopen(process_obj)


def worker_context(spec: EnvSpec) -> mp.context.BaseContext:
    # forkserver: workers fork from a clean server that has the simulator imported
    # once, never from the sim service (whose Zenoh threads must not fork). Camera
    # observations: the GL backend is decided (into os.environ) before the server
    # starts, since the server imports mujoco and workers inherit its environment.
    global _CTX
    ensure_gl_for(spec)
    if _CTX is None:
        _CTX = mp.get_context("forkserver")
        _CTX.set_forkserver_preload([*backend(spec).preload, "ebrl.envs.worker", "ebrl.envs.latency"])
    return _CTX


@dataclass
class ChunkResult:
    """What one environment did with one action chunk."""

    reward: float  # sum of rewards over the executed steps
    steps: int  # steps executed (< K when the episode ended inside the chunk)
    terminated: bool
    truncated: bool
    final_obs: np.ndarray  # observation after the last executed step (before any reset)
    next_obs: np.ndarray  # observation for the next chunk (after auto-reset if the episode ended)
    episode_return: float | None  # set when the episode ended in this chunk
    episode_length: int | None
    episode_success: bool | None = None  # set at episode end when the env reports info["success"]
    busy_s: float = 0.0  # CPU seconds spent inside env.step (useful work, excluding IPC and waiting)
    episode: int = 0  # index of the episode these steps belong to (per env, from 0)
    step_s: tuple[float, ...] = ()  # wall seconds of each env.step of the chunk
    step_cpu_s: tuple[float, ...] = ()  # CPU seconds of each env.step (the env's own cost, whoever shares the core)
    cores: tuple[int, ...] = ()  # the core each step ran on (rebinding: the core it was granted; else empty)
    helper_cpu_s: float = 0.0  # CPU seconds the env's other threads used during the chunk (a multi-threaded simulator)
    guarded: guard.Guarded = field(default_factory=guard.Guarded)  # what the checks changed (ebrl.envs.guard)

    def stepped(self) -> tuple[float, float]:
        """(CPU seconds of its steps, its other threads' included; wall seconds of its steps)."""
        return sum(self.step_cpu_s) + self.helper_cpu_s, sum(self.step_s)


def cores_used(results: Iterable[ChunkResult]) -> float:
    """Cores an env kept busy while it stepped: the CPU time of its steps, its other threads' included, over
    their wall time (about 1 for a single-threaded simulator, more for one that steps on several threads; nan
    before any step). The stepping choice watches it at run time and the allocator's profile measures it, so
    both decide cores per environment from the same number."""
    cpu = wall = 0.0
    for r in results:
        c, w = r.stepped()
        cpu, wall = cpu + c, wall + w
    return cpu / wall if wall > 0 else float("nan")


def as_obs(obs: Any) -> np.ndarray:
    return np.asarray(obs, dtype=np.float32)


def die_with_parent(parent: int) -> bool:
    """Have this process SIGKILLed when its parent dies (``PR_SET_PDEATHSIG``); False when the parent it was
    started by, ``parent``, is gone already (it died before the call, so the signal will never come)."""
    libc = ctypes.CDLL(None, use_errno=True)
    if libc.prctl(PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0) != 0:
        raise OSError(ctypes.get_errno(), "prctl(PR_SET_PDEATHSIG)")
    return os.getppid() == parent  # read after prctl: a parent that dies from now on sends the signal


def die_with(owner: int) -> bool:
    """Have this process SIGKILLed when process ``owner`` exits, whoever its parent is: a daemon thread waits on a
    pidfd of it (polls, where there are none). False when ``owner`` is gone already."""
    try:
        pidfd: int | None = os.pidfd_open(owner)
    except ProcessLookupError:
        return False
    except OSError:  # no pidfds (Linux < 5.3)
        pidfd = None

    def watch() -> None:
        if pidfd is not None:
            select.select([pidfd], [], [])  # readable once the process exited
        else:
            while _exists(owner):
                time.sleep(1.0)
        os.kill(os.getpid(), signal.SIGKILL)

    threading.Thread(target=watch, name="ebrl-owner-watch", daemon=True).start()
    return _exists(owner)


def _exists(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        pass
    return True


def adopt(owner: int | None, nice: int = 0) -> bool:
    """In a worker process, first thing: SIGINT is ignored (the sim service decides when workers stop), the
    process runs at niceness ``nice`` (``sim.nice``; before it starts a thread, so every thread it starts runs
    there too), and it dies with its parent and with ``owner`` (the sim service's pid). False: one of them is
    gone already."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if nice > os.nice(0):
        os.nice(nice - os.nice(0))
    # The parent imported this module before it forked this process: the forkserver (which preloads it) or a
    # forking sim service. Imported here (spawn, a forkserver without the preload), its pid is not known.
    parent = _IMPORTED_BY if _IMPORTED_BY != os.getpid() else os.getppid()
    return die_with_parent(parent) and (owner is None or die_with(owner))


def _worker_main(conn: Connection, spec: EnvSpec, seed: int, claim: CoreClaim | None = None,
                 cores: tuple[int, ...] | None = None, owner: int | None = None, nice: int = 0) -> None:
    """Episode ``k`` starts from ``env.reset(seed=seed + 7919 * k)``: workers given the same ``seed`` replay
    the same sequence of initial states (GRPO groups). With a ``claim`` on the sim service's core pool, every
    step runs on a core claimed from it (:mod:`ebrl.resources.corepool`). ``cores``: pinned there before the env
    is made, so every thread a simulator starts runs there too. ``owner``: the sim service's pid; the worker
    dies with it; ``nice``: its niceness (:func:`adopt`)."""
    if not adopt(owner, nice):
        return  # the sim service (or the forkserver) died before the worker got here
    if cores:
        os.sched_setaffinity(0, cores)
    if claim is not None:
        claim.register()
    try:
        _serve(conn, spec, seed, claim)
    except ParentGone:
        return


def _serve(conn: Connection, spec: EnvSpec, seed: int, claim: CoreClaim | None) -> None:
    """Answer the parent's requests on ``conn`` until it says "close" or the pipe closes."""
    served = _ServedEnv(spec, seed, claim)
    try:
        while True:
            try:
                cmd, arg = conn.recv()
            except (EOFError, OSError):
                return
            if cmd == "reset":  # arg: the index of the episode to start (a replaced worker carries on)
                conn.send(served.start(int(arg or 0), guard.Guarded()))
            elif cmd == "chunk":
                actions, observe = arg
                conn.send(served.chunk(actions, observe))
            elif cmd == "close":
                return
            else:
                conn.send(ValueError(f"unknown worker command {cmd!r}"))
    finally:
        served.env.close()


class _ServedEnv:
    """A worker's environment and its episode bookkeeping (return, length, success, episode index), carried from
    one request to the next (:func:`_serve`)."""

    obs: Any  # the last observation (set by the first reset): what a chunk of no actions reports again

    def __init__(self, spec: EnvSpec, seed: int, claim: CoreClaim | None):
        self.env = env = make_env(spec, seed=seed)
        self.seed, self.claim = seed, claim
        self.low, self.high = env.action_space.low, env.action_space.high
        self.bound = spec.max_abs_reward
        observer = lazy_observer(env) if spec.lazy_render else None  # renders only the observations that are read
        self.base, self.lazy = (observer, True) if observer is not None else (env.unwrapped, False)
        self.episode_return, self.episode_length, self.episodes = 0.0, 0, 0
        self.success: bool | None = None

    def start(self, episode: int, seen: guard.Guarded) -> np.ndarray:
        """Start episode ``episode`` from ``reset(seed=seed + 7919 * episode)``; its first observation, checked
        (``seen`` counts a non-finite one)."""
        self.episodes = episode
        self.obs, _ = self.env.reset(seed=self.seed + EPISODE_SEED_STRIDE * episode)
        self.episode_return, self.episode_length, self.success = 0.0, 0, None
        return guard.observation(as_obs(self.obs), seen)[0]

    def chunk(self, actions: np.ndarray, observe: bool) -> ChunkResult:
        """Step ``actions`` until they run out or the episode ends, when the next episode starts (auto-reset).
        ``observe``: whether the chunk's last observation is read (an episode's end always is)."""
        seen = guard.Guarded()
        started = time.thread_time()  # CPU time: a descheduled worker is not busy
        process_started = time.process_time()  # every thread's: the env's own threads too
        step_s, step_cpu, cores = [], [], []
        claim = self.claim
        core = claim.acquire() if claim is not None else None
        obs, total, steps, terminated, truncated, core = self._step(actions, observe, seen, core, step_s, step_cpu,
                                                                    cores)
        obs, broken = guard.observation(as_obs(obs), seen)
        truncated = truncated or (broken and not terminated)  # a non-finite state ends its episode
        busy = time.thread_time() - started
        helper = max(0.0, time.process_time() - process_started - busy)
        self.episode_return += total
        self.episode_length += steps
        final_obs = as_obs(obs)
        ep_ret = ep_len = ep_success = None
        episode = self.episodes
        if terminated or truncated:
            ep_ret, ep_len, ep_success = self.episode_return, self.episode_length, self.success
            obs = self.start(episode + 1, seen)
        self.obs = obs
        if claim is not None:
            claim.release(core, step_s[-1] if step_s else 0.0)
        return ChunkResult(total, steps, bool(terminated), bool(truncated), final_obs, as_obs(obs), ep_ret, ep_len,
                           ep_success, busy, episode, tuple(step_s), tuple(step_cpu), tuple(cores), helper, seen)

    def _step(self, actions: np.ndarray, observe: bool, seen: guard.Guarded, core: int | None, step_s: list[float],
              step_cpu: list[float], cores: list[int]) -> tuple[Any, float, int, bool, bool, int | None]:
        """The chunk's steps, each on a core claimed from the pool (``core``: the one held, with a claim), until
        the actions run out or the episode ends. Appends each step's wall and CPU seconds and core to ``step_s``,
        ``step_cpu`` and ``cores``; what the reward checks changed goes to ``seen``. Returns the last observation
        (unchecked), the checked rewards' sum, the steps taken, terminated, truncated and the core held now."""
        total, steps, terminated, truncated = 0.0, 0, False, False
        if not len(actions):
            return self.obs, total, steps, terminated, truncated, core
        env, claim, base, lazy, low, high, bound = (self.env, self.claim, self.base, self.lazy, self.low, self.high,
                                                    self.bound)
        for k, action in enumerate(actions):
            if k and claim is not None:
                core = claim.next(core, step_s[-1])  # keep the core, or hand it on and wait
            if lazy:  # only the chunk's last observation is read: skip rendering the others
                base.skip_observation = k < len(actions) - 1 or not observe
            t0, c0 = time.perf_counter(), time.thread_time()
            obs, reward, terminated, truncated, info = env.step(np.clip(action, low, high))
            step_s.append(time.perf_counter() - t0)
            step_cpu.append(time.thread_time() - c0)
            if core is not None:
                cores.append(core)
            if "success" in info:
                self.success = bool(self.success) or bool(info["success"])
            total += guard.reward(reward, bound, seen)
            steps += 1
            if terminated or truncated:
                break
        if lazy and base.skip_observation and (terminated or truncated):  # an episode's end is always read
            obs = base.observe()
        return obs, total, steps, terminated, truncated, core


def _cores(core: int | tuple[int, ...]) -> tuple[int, ...]:
    return (int(core),) if isinstance(core, (int, np.integer)) else tuple(int(c) for c in core)


@dataclass
class VectorChunk:
    """What a batch did with one chunk, on the host: per env (``[N]``) and per env whose episode ended (``[E]``)."""

    reward: np.ndarray  # [N] sum over the env's counted steps
    steps: np.ndarray  # [N] steps counted (< K when its episode ended inside the chunk)
    terminated: np.ndarray  # [N] bool
    truncated: np.ndarray  # [N] bool
    episode: np.ndarray  # [N] the episode the steps belong to
    next_obs: np.ndarray | None  # [N, D] the observation for the next chunk (after the reset, where one ended)
    ended: np.ndarray  # [E] the envs whose episode ended
    final_obs: np.ndarray | None  # [E, D] their observation after their last step (before the reset)
    # (next_obs and final_obs are None while they travel in shared memory: VectorWorker.chunk fills them in)
    episode_return: np.ndarray  # [E]
    episode_length: np.ndarray  # [E]
    episode_success: np.ndarray  # [E] int8: 1, 0, or -1 where the task reports no success
    busy_s: float  # CPU seconds of the chunk's steps (the whole batch)
    step_s: tuple[float, ...]  # wall seconds of each batch step
    rewards_clipped: np.ndarray | None = None  # [N] steps whose reward was clipped (ebrl.envs.guard)
    rewards_nonfinite: np.ndarray | None = None  # [N] steps whose reward was not finite
    obs_nonfinite: np.ndarray | None = None  # [N] steps whose observation was not finite (its episode ended)

    def results(self) -> list[ChunkResult]:
        """One :class:`ChunkResult` per env, as a worker process would have answered; each env's share of the
        batch's CPU time as its ``busy_s``."""
        n = len(self.reward)
        row = {int(env): j for j, env in enumerate(self.ended)}
        out = []
        for i in range(n):
            j = row.get(i)
            success = None if j is None or self.episode_success[j] < 0 else bool(self.episode_success[j])
            out.append(ChunkResult(
                reward=float(self.reward[i]), steps=int(self.steps[i]), terminated=bool(self.terminated[i]),
                truncated=bool(self.truncated[i]), final_obs=self.next_obs[i] if j is None else self.final_obs[j],
                next_obs=self.next_obs[i], episode_return=None if j is None else float(self.episode_return[j]),
                episode_length=None if j is None else int(self.episode_length[j]), episode_success=success,
                busy_s=self.busy_s / n, episode=int(self.episode[i]), guarded=guard.Guarded(
                    0 if self.rewards_clipped is None else int(self.rewards_clipped[i]),
                    0 if self.rewards_nonfinite is None else int(self.rewards_nonfinite[i]),
                    0 if self.obs_nonfinite is None else int(self.obs_nonfinite[i]))))
        return out


class WorkerFailed(RuntimeError):
    """An env worker that died or did not answer in time; the caller replaces it."""


class WorkerProcess:
    """Parent side of a worker process that answers requests over a pipe (an env worker, a vectorized group)."""

    def __init__(self, spec: EnvSpec, target: Any, args: Callable[[Connection], tuple], name: str, nice: int = 0):
        """Start ``target(child_conn, *args(child_conn), owner_pid, nice)`` in a process of the env workers'
        forkserver (``nice``: its niceness, ``sim.nice``, which it takes itself before anything else)."""
        ctx = worker_context(spec)
        self.conn, child = ctx.Pipe()
        self.proc = BareProcess(target=target, args=(child, *args(child), os.getpid(), nice), daemon=True,
                                name=name)
        self.proc.start()
        child.close()
        self.chunks_done = 0  # chunks it answered (a replaced worker that never did counts against its env)

    async def request(self, cmd: str, arg: object = None, timeout: float | None = None) -> object:
        """Send one command and await the reply; raise :class:`WorkerFailed` if the worker dies or takes
        longer than ``timeout`` seconds (it is then left for the caller to kill and replace)."""
        loop = asyncio.get_running_loop()
        fut: asyncio.Future = loop.create_future()
        fd = self.conn.fileno()

        def readable() -> None:
            loop.remove_reader(fd)
            try:
                reply = self.conn.recv()  # read even when nobody waits: the next request must not get it
            except (EOFError, OSError) as exc:
                reply = WorkerFailed(f"env worker {self.proc.pid} died ({exc!r}; exit code {self.proc.exitcode})")
            if fut.done():  # the request was cancelled (its service stopping) after the reply was on its way
                return
            if isinstance(reply, Exception):
                fut.set_exception(reply)
            else:
                fut.set_result(reply)

        try:
            self.conn.send((cmd, arg))
        except (OSError, ValueError) as exc:
            raise WorkerFailed(f"env worker {self.proc.pid} is gone ({exc!r})") from None
        loop.add_reader(fd, readable)
        try:
            return await asyncio.wait_for(fut, timeout)
        except asyncio.TimeoutError:
            raise WorkerFailed(f"env worker {self.proc.pid} did not answer {cmd!r} within {timeout:.1f} s") from None
        finally:
            loop.remove_reader(fd)

    def kill(self, close_pipe: bool = True) -> None:
        """End the process now (a dead or hung worker). ``close_pipe=False`` leaves the pipe open, so that a
        request in flight fails as for a worker that died (its caller then kills it again, closing it)."""
        if self.proc.is_alive():
            self.proc.kill()
        self.proc.join(2.0)
        if close_pipe:
            self.conn.close()

    def close(self, timeout: float = 2.0) -> None:
        try:
            self.conn.send(("close", None))
        except (OSError, ValueError):
            pass
        self.proc.join(timeout)
        if self.proc.is_alive():
            self.proc.kill()
            self.proc.join(1.0)
        self.conn.close()


class EnvWorker(WorkerProcess):
    """Parent-side handle of one env worker process."""

    def __init__(self, spec: EnvSpec, seed: int, core: int | tuple[int, ...] | None = None,
                 pool: CorePool | None = None, slot: int = 0, nice: int = 0):
        """``core``: pinned there (a core, or a set of cores for a simulator that steps on several threads,
        ``sim.cores_per_env``), every thread of it; ``pool``: every step claims a core of the pool as env
        ``slot`` of it; ``nice``: the worker's niceness (``sim.nice``)."""
        home = _cores(core) if core is not None else None
        super().__init__(spec, _worker_main,
                         lambda child: (spec, seed, CoreClaim(pool, slot, child) if pool is not None else None, home),
                         "ebrl-env", nice)
        self.slot = slot  # its place in the core pool
        self.core = core
        if core is not None:
            self.pin(core)

    def pin(self, core: int | tuple[int, ...]) -> None:
        pin_threads(self.proc.pid, _cores(core))
        self.core = core

    @property
    def home(self) -> tuple[int, ...]:
        """The cores it is pinned to (empty: it claims cores from a pool, or runs where the OS puts it)."""
        return _cores(self.core) if self.core is not None else ()

    async def reset(self, episode: int = 0) -> np.ndarray:
        """Start episode ``episode`` (its initial state is fixed by the worker's seed and the index)."""
        return await self.request("reset", episode)  # type: ignore[return-value]

    async def chunk(self, actions: np.ndarray, observe: bool = True, timeout: float | None = None) -> ChunkResult:
        """Run ``actions`` (stopping early at an episode end). ``observe=False``: the caller will not read the
        observation after the last action (more steps of the same chunk follow), so an env that can skip
        rendering does; an episode that ends is always observed."""
        result = await self.request("chunk", (actions, observe), timeout)
        self.chunks_done += 1
        return result  # type: ignore[return-value]


# --- the physical limit ---------------------------------------------------------------------


def _raw_loop(spec: EnvSpec, seed: int, core: int, seconds: float, out) -> None:
    os.sched_setaffinity(0, {core})
    env = make_env(spec, seed=seed)
    env.reset(seed=seed)
    steps, start = 0, time.perf_counter()
    while time.perf_counter() - start < seconds:
        _, _, terminated, truncated, _ = env.step(env.action_space.sample())
        steps += 1
        if terminated or truncated:
            env.reset()
    out.put(steps / (time.perf_counter() - start))
    env.close()


def raw_steps_per_s(spec: EnvSpec, cores: list[int], seconds: float = 10.0) -> float:
    """Raw simulator capacity of ``cores``: one environment per core, pinned, stepping random actions in a
    tight loop with no framework around it, all cores at once; env steps/s summed over the cores."""
    ctx = worker_context(spec)
    out = ctx.Queue()
    procs = [BareProcess(target=_raw_loop, args=(spec, i, core, seconds, out), daemon=True, name="ebrl-raw")
             for i, core in enumerate(cores)]
    for proc in procs:
        proc.start()
    try:
        return float(sum(out.get(timeout=seconds + 120) for _ in procs))
    finally:
        for proc in procs:
            proc.join(5)
            if proc.is_alive():
                proc.kill()
