"""Greedy core rebinding without the event loop: env workers hand cores to each other through shared memory.

The same policy as :class:`ebrl.sched.rebind.CoreRebinding` (the paper's greedy step scheduler, which stays
the reference and drives the replays), carried out by the env worker processes themselves. A worker with a
chunk to run claims a core of the simulation budget for each step: a free one if there is one, else it
waits. When its step ends it compares itself with the waiting envs by the paper's order (never measured
first, then the longest last step latency ``H``): it keeps the core and steps on, or hands the core to the
first waiter and waits its turn. A handed core goes straight to its new env, which pins itself to it; the
sim service's event loop only sends whole chunks and collects their results.

Shared state (one :class:`CorePool` per sim service, passed to every worker it starts): per env slot its
``H``, whether it waits and the core granted to it, and a semaphore it waits on; per core whether it is in
the budget, free, and which slot holds it. One lock guards it all; every critical section is a few numpy
operations on arrays of the env count.

``mode`` switches the whole pool at run time (``sim.core_rebinding = "auto"`` decides it,
:mod:`ebrl.sched.stepchoice`): :data:`REBIND` as above, :data:`PINNED` each env runs its whole chunk on its
home core (env slot ``i`` on budget core ``i mod len(budget)``), shared with the envs pinned there.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import time
from multiprocessing.connection import Connection

import numpy as np

PINNED, REBIND = 0, 1
_NEVER = np.inf  # the priority of an env whose latency was never measured: it goes first


def pin_threads(pid: int, cores: set[int] | tuple[int, ...] | list[int]) -> None:
    """Pin every thread of process ``pid`` to ``cores``: ``sched_setaffinity`` moves one thread, and a
    simulator's own threads, started before, would stay where they were (step-level rebinding moves only the
    stepping thread, which is why it is not for multi-threaded simulators: :mod:`ebrl.sched.stepchoice`)."""
    cores = set(cores)
    try:
        tids = [int(t) for t in os.listdir(f"/proc/{pid}/task")]
    except OSError:
        tids = [pid]
    for tid in tids:
        try:
            os.sched_setaffinity(tid, cores)
        except (ProcessLookupError, PermissionError):  # a thread that just ended
            pass


class PoolBroken(RuntimeError):
    """The pool's lock stayed held (a worker died inside a critical section): the sim service must restart."""


class ParentGone(Exception):
    """The sim service closed the worker's pipe while the worker waited for a core."""


class CorePool:
    """The shared core-token pool of one sim service's env workers (picklable to a worker at its start)."""

    def __init__(self, slots: int, cores: list[int], mode: int = REBIND, ctx: mp.context.BaseContext | None = None):
        if not cores:
            raise ValueError("the simulation core budget is empty")
        ctx = ctx or mp.get_context("forkserver")
        self.slots, self.ncores = slots, max(os.cpu_count() or 1, max(cores) + 1)
        self.lock = ctx.Lock()
        self.sems = [ctx.Semaphore(0) for _ in range(slots)]
        self._f = ctx.RawArray("d", 4 * slots)  # H, grant time, handoff gaps: sum and count
        self._i = ctx.RawArray("q", 3 * slots + 3 * self.ncores + 3)
        self._views()
        self.H[:] = _NEVER
        self.grant[:] = -1
        self.owner[:] = -1
        self.mode_flag[0] = mode
        self._set_budget(cores)

    def _views(self) -> None:
        f = np.frombuffer(self._f, dtype=np.float64)
        i = np.frombuffer(self._i, dtype=np.int64)
        s, n = self.slots, self.ncores
        self.H, self.granted_at, self.gap_sum, self.gap_n = f[:s], f[s:2 * s], f[2 * s:3 * s], f[3 * s:]
        self.waiting, self.grant, self.pid = i[:s], i[s:2 * s], i[2 * s:3 * s]
        c = 3 * s
        self.budget, self.free, self.owner = i[c:c + n], i[c + n:c + 2 * n], i[c + 2 * n:c + 3 * n]
        self.mode_flag, self.handoffs, self.rebinds = (i[c + 3 * n + k:c + 3 * n + k + 1] for k in range(3))

    def __getstate__(self):
        return {k: v for k, v in self.__dict__.items() if not isinstance(v, np.ndarray)}

    def __setstate__(self, state):
        self.__dict__.update(state)
        self._views()

    # --- under the lock ---------------------------------------------------------------------------------

    def _best_waiter(self) -> int:
        """The waiting slot the paper's order picks (never measured, then longest H; ties: lowest slot), -1."""
        if not self.waiting.any():
            return -1
        return int(np.argmax(np.where(self.waiting == 1, self.H, -1.0)))

    def _give(self, core: int) -> None:
        """A core of the budget became available: to the best waiter, else back to the free set."""
        w = self._best_waiter()
        if w < 0:
            self.owner[core], self.free[core] = -1, 1
            return
        self.waiting[w], self.grant[w], self.owner[core] = 0, core, w
        try:  # the waiter wakes on the granted core, not on the (busy) one it slept on
            os.sched_setaffinity(int(self.pid[w]), {core})
        except OSError:  # gone: the sim service reclaims its slot
            pass
        self.granted_at[w] = time.perf_counter()
        self.handoffs[0] += 1
        self.sems[w].release()

    def _set_budget(self, cores: list[int]) -> None:
        self.budget[:] = 0
        self.budget[list(cores)] = 1
        self.free[self.budget == 0] = 0  # a removed core that is busy retires when its step ends
        for core in cores:
            if self.owner[core] < 0 and not self.free[core]:
                self._give(core)

    # --- the sim service's side -------------------------------------------------------------------------

    def cores(self) -> list[int]:
        return [int(c) for c in np.flatnonzero(self.budget)]

    def set_budget(self, cores: list[int]) -> None:
        """A new simulation core budget, used from the next step."""
        if not cores:
            raise ValueError("the simulation core budget is empty")
        self._hold()
        try:
            self._set_budget(cores)
        finally:
            self.lock.release()

    def set_mode(self, mode: int) -> None:
        """PINNED or REBIND, from each worker's next chunk on."""
        self.mode_flag[0] = mode

    @property
    def mode(self) -> int:
        return int(self.mode_flag[0])

    def reclaim(self, slot: int) -> None:
        """The worker of ``slot`` died or hung and was killed: give back what it held, forget its wait."""
        self._hold()
        try:
            self.waiting[slot] = 0
            self.H[slot] = _NEVER
            while self.sems[slot].acquire(False):  # a grant it never took
                pass
            for core in np.flatnonzero(self.owner == slot):
                self.owner[core] = -1
                if self.budget[core]:
                    self._give(int(core))
        finally:
            self.lock.release()

    def _hold(self) -> None:
        if not self.lock.acquire(timeout=5.0):
            raise PoolBroken("the env workers' core pool stayed locked for 5 s (a worker died holding it)")

    def counters(self) -> tuple[int, int, float]:
        """(handoffs, rebinds, mean seconds a handed core stood idle before its new env stepped on it)."""
        return int(self.handoffs[0]), int(self.rebinds[0]), float(self.gap_sum.sum() / max(1.0, self.gap_n.sum()))

    def home(self, slot: int) -> int:
        cores = self.cores()
        return cores[slot % len(cores)]


class CoreClaim:
    """One env worker's side of the pool: claim a core per step, keep or hand it on, release it."""

    def __init__(self, pool: CorePool, slot: int, conn: Connection | None = None):
        self.pool, self.slot, self.conn = pool, slot, conn
        self.pinned: int | None = None
        self.rebinds = 0

    def register(self) -> None:
        """In the worker, before its first step: the pool moves it by its pid when it grants it a core."""
        self.pool.pid[self.slot] = os.getpid()

    def _pin(self, core: int) -> int:
        if core != self.pinned:
            os.sched_setaffinity(0, {core})
            if self.pinned is not None:
                self.rebinds += 1
            self.pinned = core
        return core

    def _wait(self) -> int:
        """Wait (lock not held) for a core to be granted; then pin to it and count the gap it stood idle."""
        pool, slot = self.pool, self.slot
        while not pool.sems[slot].acquire(timeout=1.0):
            if self.conn is not None and self.conn.poll():  # the parent closed the pipe (or stops us)
                raise ParentGone
        core = int(pool.grant[slot])
        if core != self.pinned:  # the granter already moved this process there
            self.rebinds += self.pinned is not None
            self.pinned = core
        gap = time.perf_counter() - pool.granted_at[slot]
        pool.gap_sum[slot] += gap  # only this worker writes its slot's entries
        pool.gap_n[slot] += 1
        return core

    def acquire(self) -> int | None:
        """A core for the first step of a chunk (None: pinned mode, the worker runs on its home core)."""
        pool = self.pool
        if pool.mode == PINNED:
            home = pool.home(self.slot)
            if home != self.pinned:  # the whole process, a simulator's own threads too (rarely: a new home)
                pin_threads(os.getpid(), {home})
            self._pin(home)
            return None
        with pool.lock:
            free = np.flatnonzero(pool.free)
            if len(free):
                core = self.pinned if self.pinned is not None and pool.free[self.pinned] else int(free[0])
                pool.free[core], pool.owner[core] = 0, self.slot
            else:
                pool.waiting[self.slot] = 1
                core = -1
        return self._pin(core) if core >= 0 else self._wait()

    def next(self, core: int | None, latency: float) -> int | None:
        """After a step (more of the chunk follows): keep the core unless a waiter goes first by the paper's
        order; then wait for another."""
        if core is None:
            return None
        pool, slot = self.pool, self.slot
        with pool.lock:
            pool.H[slot] = latency
            retired = not pool.budget[core]
            w = pool._best_waiter()
            if not retired and (w < 0 or pool.H[w] <= latency):
                return core
            pool.owner[core] = -1
            if not retired:
                pool._give(core)
            free = np.flatnonzero(pool.free)
            if len(free):  # only when the core retired and another is free
                core = int(free[0])
                pool.free[core], pool.owner[core] = 0, slot
            else:
                pool.waiting[slot] = 1
                core = -1
        return self._pin(core) if core >= 0 else self._wait()

    def release(self, core: int | None, latency: float) -> None:
        """The chunk is done: the core goes to the best waiter or back to the free set."""
        if core is None:
            return
        pool = self.pool
        with pool.lock:
            pool.H[self.slot] = latency
            pool.owner[core] = -1
            if pool.budget[core]:
                pool._give(core)
            pool.rebinds[0] += self.rebinds
        self.rebinds = 0
