"""Elastic resource allocation (paper, Algorithm 1 "Elastic resource allocation", Eq. theta).

Pure functions over measured lookup tables, no I/O. Names follow the paper: ``c_env``, ``E``,
``s_sim``/``s_g``/``s_t`` quotas, ``B_g``/``B_t`` batches, ``T_s``/``T_r``/``T_t`` rates, ``Theta``.
:func:`elastic_allocation` is the algorithm, one function in the order of the paper's block, whose comments
cite its lines by number and label (line 1 alloc-cores ... line 20 alloc-return; algpseudocode numbers the
else, end if and end while lines too, so the loop is lines 6-17 and the endpoints lines 18-19).

Units. Rates are in one unit, chunk-steps per second (the caller normalises each stage's measurement).
Quotas are integers out of ``total``: SM percent (total 100) on a GPU machine, cores on a CPU-only one.

Lookups are conservative. Tables are measured on grids (s in {10, 20, ...}); a quota between grid points
reads the largest measured quota below it (never predict more than was measured), and a quota below the
grid reads 0 (that stage cannot run there). So every stage rate is a step function of its quota.

Robustness, where the paper leaves it open (its "AUTHOR CHECK" notes):

* Infeasible split: s_sim* + s_g_min + s_t_min > total raises :class:`InfeasibleError` naming the numbers,
  as does a memory budget that no (B_g, B_t) pair fits.
* Non-monotonic tables: the bisection assumes T_r non-decreasing and T_t non-increasing in s_g. It is
  checked on the table grid inside [lo, hi] first, together with memory coupling (a budget that does not
  fit both stages' fastest batches lets the best pair switch with s_g, which breaks the premise even for
  monotone tables); where it fails, a scan replaces the bisection. The scan evaluates only the breakpoints
  of the step functions (where a gen or train lookup changes): exactly as good as every integer s_g, and
  much cheaper. Where the premise holds the bisection is exact too, so lines 5-19 always return the best
  split for the simulator lines 1-3 chose.
* The search never returns a configuration with Theta = 0 (a stage below its grid): if neither endpoint
  is feasible it falls back to the scan, and if the scan finds nothing the callers raise InfeasibleError.

A known gap of line 3: the knee quota is reserved even when the simulator is not the bottleneck, and that
quota is lost to generation and training (up to ~40 % of Theta on the benchmark's tables). ``allocate(...,
scan_sim=True)`` scans the profiled simulator configurations instead (:func:`scan_simulators`, lines 1-3
replaced), which finds the optimum.

:func:`allocate` is Algorithm 1 on a GPU machine; :func:`allocate_cpu` adapts it to a CPU-only machine,
where every stage draws from the same cores (see there); :func:`exhaustive` is the reference optimum the
tests and ``benchmarks/allocator_quality.py`` compare against; :func:`refine` is the runtime adaptation.
"""

from __future__ import annotations

import math
from bisect import bisect_right
from collections.abc import Callable, Hashable
from dataclasses import dataclass, field, replace
from functools import cached_property
from typing import Any


class InfeasibleError(ValueError):
    """No configuration satisfies the quota, core and memory constraints with a positive throughput."""


@dataclass(frozen=True)
class _Curve:
    """One measured rate curve over an ascending quota grid (one batch size, or one (c_env, E))."""

    quotas: tuple[int, ...]
    rates: tuple[float, ...]

    def at(self, s: int) -> float:
        """Rate at the largest grid quota <= s; 0 below the grid."""
        i = bisect_right(self.quotas, s)
        return self.rates[i - 1] if i else 0.0

    def non_decreasing_on(self, a: int, b: int) -> bool:
        """Whether ``at`` is non-decreasing over the quotas a..b (it only changes at grid quotas)."""
        values = [self.at(a)] + [r for q, r in zip(self.quotas, self.rates) if a < q <= b]
        return all(x <= y for x, y in zip(values, values[1:]))


def _curves(table: dict[tuple[int, ...], float], split: Callable[[tuple], tuple[Hashable, int]]) -> dict:
    """Group a table into curves: ``split(key)`` gives (curve id, quota)."""
    points: dict[Hashable, list[tuple[int, float]]] = {}
    for key, rate in table.items():
        curve_id, quota = split(key)
        points.setdefault(curve_id, []).append((quota, float(rate)))
    return {
        curve_id: _Curve(tuple(q for q, _ in sorted(pts)), tuple(r for _, r in sorted(pts)))
        for curve_id, pts in sorted(points.items())
    }


@dataclass
class Profiles:
    """Measured stage lookup tables (the paper's P_sim, P_gen, P_train).

    Treat as immutable once built: the curves are indexed on first use, and :func:`refine` returns new
    tables. CPU simulators need no GPU quota and are profiled at s_sim = 0.
    """

    sim: dict[tuple[int, int, int], float]  # (c_env cores per env, E concurrent envs, s_sim quota) -> T_sim
    gen: dict[tuple[int, int], float]  # (s_g quota, B_g batch) -> T_gen
    train: dict[tuple[int, int], float]  # (s_t quota, B_t batch) -> T_train
    gen_mem: dict[int, float] = field(default_factory=dict)  # B_g -> bytes generation needs (absent: 0)
    train_mem: dict[int, float] = field(default_factory=dict)  # B_t -> bytes training needs (absent: 0)
    sim_cores_used: float | None = None  # cores one env kept busy while stepping alone (the c_env probe)

    def with_c_env(self, c_env: int) -> Profiles:
        """The same tables with the simulator's restricted to ``c_env`` cores per env (unchanged where that
        was not profiled): a re-plan keeps the cores per env the run started with, since the env workers are
        pinned by it; the core budget and the other stages' shares are what re-plans move."""
        if not any(key[0] == c_env for key in self.sim):
            return self
        return replace(self, sim={key: rate for key, rate in self.sim.items() if key[0] == c_env})

    def P_sim(self, c_env: int, E: int, s_sim: int) -> float:
        """T_sim, read conservatively in s_sim; 0 for an unprofiled (c_env, E). Likewise P_gen and P_train."""
        curve = self._sim_curves.get((c_env, E))
        return curve.at(s_sim) if curve else 0.0

    def P_gen(self, s_g: int, B_g: int) -> float:
        curve = self._gen_curves.get(B_g)
        return curve.at(s_g) if curve else 0.0

    def P_train(self, s_t: int, B_t: int) -> float:
        curve = self._train_curves.get(B_t)
        return curve.at(s_t) if curve else 0.0

    def memory(self, B_g: int, B_t: int) -> float:
        """Device memory generation at B_g and training at B_t need together."""
        return self.gen_mem.get(B_g, 0.0) + self.train_mem.get(B_t, 0.0)

    @cached_property
    def _sim_curves(self) -> dict[tuple[int, int], _Curve]:
        return _curves(self.sim, lambda key: (key[:2], key[2]))

    @cached_property
    def _gen_curves(self) -> dict[int, _Curve]:
        return _curves(self.gen, lambda key: (key[1], key[0]))

    @cached_property
    def _train_curves(self) -> dict[int, _Curve]:
        return _curves(self.train, lambda key: (key[1], key[0]))

    def to_json(self) -> dict[str, Any]:
        """A dict ``json.dumps`` accepts: tuple keys become "a,b,c" strings, batch keys strings."""
        return {
            "sim": _keys_to_str(self.sim),
            "gen": _keys_to_str(self.gen),
            "train": _keys_to_str(self.train),
            "gen_mem": {str(b): m for b, m in self.gen_mem.items()},
            "train_mem": {str(b): m for b, m in self.train_mem.items()},
            "sim_cores_used": self.sim_cores_used,
        }

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> Profiles:
        """Inverse of :meth:`to_json`."""
        return cls(
            sim=_keys_from_str(data["sim"]),
            gen=_keys_from_str(data["gen"]),
            train=_keys_from_str(data["train"]),
            gen_mem={int(b): float(m) for b, m in data.get("gen_mem", {}).items()},
            train_mem={int(b): float(m) for b, m in data.get("train_mem", {}).items()},
            sim_cores_used=data.get("sim_cores_used"),
        )


def _keys_to_str(table: dict[tuple[int, ...], float]) -> dict[str, float]:
    return {",".join(str(k) for k in key): rate for key, rate in table.items()}


def _keys_from_str(table: dict[str, float]) -> dict:
    return {tuple(int(k) for k in key.split(",")): float(rate) for key, rate in table.items()}


@dataclass
class Allocation:
    """A configuration C* and its predicted stage rates."""

    c_env: int  # cores per environment
    E: int  # concurrent environments
    s_sim: int  # simulator quota: SM % on a GPU machine; its cores (E * c_env) on a CPU-only one
    s_gen: int
    s_train: int
    B_gen: int
    B_train: int
    T_sim: float
    T_gen: float
    T_train: float
    theta: float  # min(min(T_sim, T_gen), T_train)
    evaluations: int  # generation-quota candidates evaluated (each one a best-batch-pair search)
    method: str  # "bisection" | "scan" (fallback) | "exhaustive" | "shared" (allocate_cpu, shared model cores)


def theta(T_sim: float, T_gen: float, T_train: float) -> float:
    """Eq. theta: rollout T_r = min(T_sim, T_gen) overlaps training, so Theta = min(T_r, T_train)."""
    return min(min(T_sim, T_gen), T_train)


def _time_shared(T_gen: float, T_train: float) -> float:
    """Rate of generation and training taking turns on the same cores: each chunk-step costs 1/T_gen + 1/T_train
    seconds of them, so both run at the harmonic combination (0 if either cannot run)."""
    return T_gen * T_train / (T_gen + T_train) if T_gen > 0 and T_train > 0 else 0.0


@dataclass(frozen=True)
class _Point:
    """One generation quota evaluated with its best feasible batch pair (Algorithm 1, lines 7-11)."""

    s_g: int
    s_t: int
    B_g: int
    B_t: int
    T_r: float
    T_gen: float
    T_train: float
    theta: float


def _best_pair(profiles: Profiles, T_s: float, s_g: int, s_t: int, M_gpu: float, shared: bool = False) -> _Point:
    """Line 9: the (B_g, B_t) with gen_mem + train_mem <= M_gpu that maximises Theta at (s_g, s_t).

    Ties (common: Theta is capped by T_s or by one stage) go to the larger T_r + T_t, so the line-12
    comparison sees what the non-bottleneck stage can do rather than an arbitrarily small batch. Theta may be
    0 here (a quota below a stage's grid): the comparison still points the search the right way, and the
    caller never returns such a point. ``shared``: s_g = s_t cores time-shared, see :func:`_time_shared`.
    Callers check first (:func:`_require_batch_pair`) that some pair fits M_gpu.
    """
    best, best_key = None, None
    for B_g, gen in profiles._gen_curves.items():
        for B_t, train in profiles._train_curves.items():
            if profiles.memory(B_g, B_t) > M_gpu:
                continue
            T_gen, T_train = gen.at(s_g), train.at(s_t)
            if shared:
                T_gen = T_train = _time_shared(T_gen, T_train)
            T_r = min(T_s, T_gen)
            key = (min(T_r, T_train), T_r + T_train)
            if best_key is None or key > best_key:
                best, best_key = _Point(s_g, s_t, B_g, B_t, T_r, T_gen, T_train, key[0]), key
    assert best is not None, "_require_batch_pair was not called"
    return best


def _require_batch_pair(profiles: Profiles, M_gpu: float) -> None:
    """Memory does not depend on quotas, so a budget that no pair fits is infeasible everywhere: say so first."""
    if not profiles.gen or not profiles.train:
        raise InfeasibleError("the generation or the training profile is empty")
    need, B_g, B_t = min((profiles.memory(g, t), g, t) for g in profiles._gen_curves for t in profiles._train_curves)
    if need > M_gpu:
        raise InfeasibleError(f"no batch pair fits M_gpu={M_gpu:g} bytes: the smallest, B_g={B_g} with B_t={B_t}, "
                              f"needs {need:g}")


def _bisection_applies(profiles: Profiles, lo: int, hi: int, R: int, M_gpu: float) -> bool:
    """The bisection's premise on [lo, hi]: T_r non-decreasing and T_t non-increasing in s_g.

    Checked on the tables: every P_gen curve non-decreasing in s_g, every P_train curve non-decreasing in
    s_t = R - s_g, and the memory budget leaving each stage its fastest batch (every batch that is fastest for
    generation somewhere in [lo, hi] fits with every batch fastest for training somewhere in [R - hi, R - lo]),
    so line 9 follows the stage-wise best curves. Where memory binds, the best pair can switch with s_g (a larger
    B_g bought with a smaller B_t): T_r and T_t then jump the wrong way and Theta can have two peaks.
    """
    gen, train = profiles._gen_curves, profiles._train_curves
    monotone = all(c.non_decreasing_on(lo, hi) for c in gen.values()) and all(
        c.non_decreasing_on(R - hi, R - lo) for c in train.values()
    )
    fast_gen, fast_train = _fastest_batches(gen, lo, hi), _fastest_batches(train, R - hi, R - lo)
    return monotone and all(profiles.memory(g, t) <= M_gpu for g in fast_gen for t in fast_train)


def _fastest_batches(curves: dict[int, _Curve], a: int, b: int) -> set[int]:
    """The fastest batch at a and at every grid quota in (a, b] (where some curve, so the fastest, can change)."""
    quotas = {a} | {q for curve in curves.values() for q in curve.quotas if a < q <= b}
    return {max(curves, key=lambda B: curves[B].at(q)) for q in quotas}


def _breakpoints(profiles: Profiles, lo: int, hi: int, R: int) -> list[int]:
    """The s_g in [lo, hi] where Theta can change: lo, each P_gen grid quota, and each s_g where s_t = R - s_g
    drops below a P_train grid quota q (s_g = R - q + 1). Both lookups, hence Theta, are constant in between,
    so the best breakpoint is as good as the best integer s_g."""
    points = {lo}
    for curve in profiles._gen_curves.values():
        points.update(q for q in curve.quotas if lo < q <= hi)
    for curve in profiles._train_curves.values():
        points.update(R - q + 1 for q in curve.quotas if lo < R - q + 1 <= hi)
    return sorted(points)


def choose_c_env(profiles: Profiles, N: int) -> tuple[int, int]:
    """Lines 1-2 (alloc-cores, alloc-concurrency): c_env* and E = floor(N / c_env*).

    E is read on the profiled grid: the largest profiled E up to floor(N / c_env). Line 1 compares the profiled
    cores per environment by their simulator capacity at that E: the best T_sim over its profiled s_sim, which
    is the largest s_sim's for a monotone table. Ties go to fewer cores per environment.
    """
    best, best_rate = None, -1.0
    for c_env in sorted({c for c, _ in profiles._sim_curves}):
        E = max((E for c, E in profiles._sim_curves if c == c_env and E <= N // c_env), default=None)
        if E is not None and max(profiles._sim_curves[c_env, E].rates) > best_rate:
            best, best_rate = (c_env, E), max(profiles._sim_curves[c_env, E].rates)
    if best is None:
        smallest = min((c * E for c, E in profiles._sim_curves), default=None)
        raise InfeasibleError(f"no profiled simulator configuration fits N={N} cores (smallest needs {smallest})")
    return best


def _infeasible_split(s_sim: int, s_g_min: int, s_t_min: int, total: int) -> InfeasibleError:
    """Line 5 with hi < lo: the simulator's quota and the two minimum quotas do not fit in ``total``."""
    return InfeasibleError(f"infeasible split: s_sim*={s_sim} + s_g_min={s_g_min} + s_t_min={s_t_min} = "
                           f"{s_sim + s_g_min + s_t_min} exceeds total={total}")


def elastic_allocation(profiles: Profiles, *, N: int | None = None, total: int = 100, M_gpu: float = math.inf,
                       s_g_min: int, s_t_min: int, knee: float = 0.05, simulator: tuple[int, int, int] | None = None,
                       remote_sim: float = 0.0) -> Allocation:
    """Algorithm 1, in the order of the paper's block; each comment names the line it implements, with its label.

    Require: the profiles, N simulation cores, the memory budget M_gpu; quotas are out of ``total`` (the
    paper's 100). Ensure: C*, whose ``evaluations`` counts the generation quotas evaluated and whose ``method``
    is "bisection", or "scan" where the tables break the bisection's premise or no endpoint has a positive
    Theta (module docstring). C* is returned even when its Theta is 0 (no split gives every stage a profiled
    rate); the callers raise, each naming its own setting. InfeasibleError: no batch pair fits M_gpu, no
    simulator configuration fits N (line 1), or the minimum quotas do not fit next to the simulator's (line 5).

    The wrappers: :func:`scan_simulators` gives ``simulator`` = (c_env, E, s_sim) in place of lines 1-3 (N is
    then not needed), and ``remote_sim``, simulation on other hosts in decisions/s, is added to T_s at line 4.
    """
    _require_batch_pair(profiles, M_gpu)  # Require: some (B_g, B_t) fits M_gpu, whatever the quotas
    if simulator is None:
        if N is None:
            raise TypeError("elastic_allocation needs N (simulation cores) to choose the simulator (lines 1-3)")
        c_env, E = choose_c_env(profiles, N)  # line 1 (alloc-cores): c_env*; line 2 (alloc-concurrency): E
        # line 3 (alloc-sim-quota): the knee, the smallest profiled s_sim within `knee` of the best T_sim at (c_env, E)
        curve = profiles._sim_curves[c_env, E]
        s_sim = next(q for q, r in zip(curve.quotas, curve.rates) if r >= (1 - knee) * max(curve.rates))
    else:
        c_env, E, s_sim = simulator
    T_s = profiles.P_sim(c_env, E, s_sim) + remote_sim  # line 4 (alloc-sim-rate)
    R = total - s_sim  # the quota left to generation and training (100 - s_sim* in the paper)
    lo, hi = s_g_min, R - s_t_min  # line 5 (alloc-bounds)
    if hi < lo:
        raise _infeasible_split(s_sim, s_g_min, s_t_min, total)
    evaluated: dict[int, _Point] = {}  # s_g -> lines 8-11 there, each quota evaluated once

    def evaluate(s_g: int) -> _Point:
        if s_g not in evaluated:
            s_t = R - s_g  # line 8 (alloc-train-quota)
            # line 9 (alloc-batches): the best feasible (B_g, B_t); lines 10-11 (alloc-rollout-rate,
            # alloc-train-rate): T_r = min(T_s, P_gen(s_g, B_g)) and T_t = P_train(s_t, B_t) with it
            evaluated[s_g] = _best_pair(profiles, T_s, s_g, s_t, M_gpu)
        return evaluated[s_g]

    best, method = None, "bisection"
    if _bisection_applies(profiles, lo, hi, R, M_gpu):  # the premise of lines 6-17 (module docstring)
        while hi - lo > 1:  # line 6 (alloc-loop)
            s_g = (lo + hi) // 2  # line 7 (alloc-gen-quota)
            point = evaluate(s_g)  # lines 8-11
            if point.T_r > point.T_train:  # line 12 (alloc-compare): rollout is faster, give training more
                hi = s_g  # line 13 (alloc-upper)
            else:  # line 14 (alloc-else)
                lo = s_g  # line 15 (alloc-lower)
        # line 18 (alloc-endpoints): both endpoints with their pairs; line 19 (alloc-select): the higher Theta
        best = max(evaluate(lo), evaluate(hi), key=lambda p: p.theta)  # ties: lo
    if best is None or best.theta <= 0:  # no premise, or no endpoint runs every stage: the exact scan instead
        best, method = max((evaluate(s_g) for s_g in _breakpoints(profiles, s_g_min, R - s_t_min, R)),
                           key=lambda p: p.theta), "scan"
    return Allocation(c_env, E, s_sim, best.s_g, best.s_t, best.B_g, best.B_t, T_s, best.T_gen, best.T_train,
                      best.theta, len(evaluated), method)  # line 20 (alloc-return): C*


def _time_shared_models(profiles: Profiles, simulator: tuple[int, int, int], k: int, remote_sim: float) -> Allocation:
    """The CPU adaptation where generation and training cannot be pinned apart: they time-share the same k cores
    (rates combined by :func:`_time_shared`), so there is no split to search; line 9 once, at s_g = s_t = k."""
    c_env, E, s_sim = simulator
    T_s = profiles.P_sim(c_env, E, s_sim) + remote_sim  # line 4
    point = _best_pair(profiles, T_s, k, k, math.inf, shared=True)  # line 9
    return Allocation(c_env, E, s_sim, k, k, point.B_g, point.B_t, T_s, point.T_gen, point.T_train, point.theta, 1,
                      "shared")


def scan_simulators(profiles: Profiles, simulators: list[tuple[int, int, int]], *, total: int, M_gpu: float,
                    s_g_min: int, s_t_min: int, remote_sim: float = 0.0,
                    shared_cores: int | None = None) -> Allocation | None:
    """Algorithm 1 with lines 1-3 replaced by a scan: :func:`elastic_allocation` (lines 4-20) for each simulator
    configuration (c_env, E, s_sim), keeping the best Theta; None when no configuration's Theta is positive.

    Each configuration must leave s_g_min + s_t_min of ``total`` (line 5). They are tried fastest simulator
    first; one whose T_s is no higher than the best Theta so far is skipped without a search, since Theta <= T_s.
    ``evaluations`` sums over the scan. ``shared_cores`` = k: generation and training time-share k cores
    instead (:func:`allocate_cpu`). ``remote_sim``: simulation on other hosts (decisions/s), added to every T_s.
    """
    rated = sorted(((profiles.P_sim(*sim) + remote_sim, sim) for sim in simulators), key=lambda c: -c[0])
    best, evaluations = None, 0
    for T_s, sim in rated:
        if best is not None and T_s <= best.theta:
            break
        if shared_cores is None:
            alloc = elastic_allocation(profiles, total=total, M_gpu=M_gpu, s_g_min=s_g_min, s_t_min=s_t_min,
                                       simulator=sim, remote_sim=remote_sim)
        else:
            alloc = _time_shared_models(profiles, sim, shared_cores, remote_sim)
        evaluations += alloc.evaluations
        if alloc.theta > 0 and (best is None or alloc.theta > best.theta):
            best = alloc
    return None if best is None else replace(best, evaluations=evaluations)


def allocate(profiles: Profiles, *, N: int, total: int = 100, M_gpu: float = math.inf, s_g_min: int, s_t_min: int,
             knee: float = 0.05, scan_sim: bool = False) -> Allocation:
    """Algorithm 1 on a GPU machine (:func:`elastic_allocation`): N simulation cores, quotas out of ``total``
    (SM %), memory budget M_gpu. InfeasibleError when no configuration gives every stage a profiled rate.

    The simulator is settled first (lines 1-4: cores per env, concurrency, knee quota, its rate), then the rest
    of the GPU is bisected between generation and training (lines 5-19), or scanned when the tables break the
    bisection's premise.

    ``scan_sim`` (not in the paper): lines 1-3 become an outer scan (:func:`scan_simulators`) over every
    profiled simulator configuration (c_env, E, s_sim) that fits N cores, each followed by lines 4-20. The knee
    reserves the simulator's full capacity even when it is not the bottleneck, and a smaller E can reach the
    needed rate on a smaller quota; either way quota is missing from generation and training
    (benchmarks/allocator_quality.py measures it). The inner search being exact, this finds the optimum, at a
    fraction of :func:`exhaustive`'s evaluations.
    """
    if scan_sim:
        _require_batch_pair(profiles, M_gpu)
        configs = [(c, E, s_sim) for (c, E), curve in profiles._sim_curves.items() if c * E <= N
                   for s_sim in curve.quotas]
        if not configs:
            raise InfeasibleError(f"no profiled simulator configuration fits N={N} cores")
        feasible = [sim for sim in configs if total - sim[2] - s_t_min >= s_g_min]  # line 5: lo <= hi
        if not feasible:
            raise _infeasible_split(min(s_sim for _, _, s_sim in configs), s_g_min, s_t_min, total)
        alloc = scan_simulators(profiles, feasible, total=total, M_gpu=M_gpu, s_g_min=s_g_min, s_t_min=s_t_min)
    else:
        alloc = elastic_allocation(profiles, N=N, total=total, M_gpu=M_gpu, s_g_min=s_g_min, s_t_min=s_t_min,
                                   knee=knee)
    if alloc is None or alloc.theta <= 0:
        raise InfeasibleError(f"no split of the quota left after the simulator (s_g >= {s_g_min}, s_t >= {s_t_min}) "
                              f"gives simulation, generation and training a profiled rate")
    return alloc


def allocate_cpu(profiles: Profiles, *, N: int, s_g_min: int = 1, s_t_min: int = 1,
                 shared_model_cores: int | None = None, remote_sim: float = 0.0, local_sim: bool = True) -> Allocation:
    """Algorithm 1 adapted to a CPU-only machine: simulation, generation and training share the same N cores.

    Quotas are cores and total = N. The simulator's quota is its core count E * c_env, so it competes with
    generation and training and no GPU knee can settle it. The CPU adaptation keeps line 1 (c_env*, on the
    N - s_g_min - s_t_min cores the simulator may take) and turns lines 2-3 into an outer scan
    (:func:`scan_simulators`): every profiled E that fits, with s_sim = c_env* * E, each followed by lines 4-20
    unchanged (the cores left bisected between generation and training); the best Theta is kept.
    ``evaluations`` sums over the outer scan.

    ``shared_model_cores`` = k: generation and training are not split but time-share the same k cores (a
    machine too small to pin them apart); their rates combine as in :func:`_time_shared`, the simulator gets
    at most N - k cores, and s_gen = s_train = k in the result (method "shared").

    Several hosts: ``remote_sim`` is the simulation capacity of the other hosts (decisions/s), added to T_s,
    so the more there is, the fewer of these cores the simulator takes. ``local_sim = False``: this host
    simulates nothing; all N cores go to generation and training (c_env = E = s_sim = 0, T_s = remote_sim).
    """
    if not local_sim:
        _require_batch_pair(profiles, math.inf)
        alloc = scan_simulators(profiles, [(0, 0, 0)], total=N, M_gpu=math.inf, s_g_min=s_g_min, s_t_min=s_t_min,
                                remote_sim=remote_sim, shared_cores=None if shared_model_cores is None else N)
        if alloc is None:
            raise InfeasibleError(f"no split of N={N} cores between generation and training has a profiled rate "
                                  f"(simulation on other hosts: {remote_sim:g} decisions/s)")
        return alloc
    reserved = shared_model_cores if shared_model_cores is not None else s_g_min + s_t_min
    budget = N - reserved  # cores the simulator may take
    if budget < 1:
        what = f"shared_model_cores={reserved}" if shared_model_cores is not None else (
            f"s_g_min={s_g_min} + s_t_min={s_t_min}")
        raise InfeasibleError(f"a CPU-only allocation needs at least {reserved + 1} cores ({what} + 1 for the "
                              f"simulator), N={N}")
    _require_batch_pair(profiles, math.inf)
    c_env, _ = choose_c_env(profiles, budget)  # line 1
    simulators = [(c_env, E, c_env * E) for c, E in profiles._sim_curves if c == c_env and c * E <= budget]
    alloc = scan_simulators(profiles, simulators, total=N, M_gpu=math.inf, s_g_min=s_g_min, s_t_min=s_t_min,
                            remote_sim=remote_sim, shared_cores=shared_model_cores)
    if alloc is None:
        raise InfeasibleError(f"no split of N={N} cores gives simulation, generation and training a profiled rate")
    return alloc


def exhaustive(profiles: Profiles, *, N: int, total: int = 100, M_gpu: float = math.inf, s_g_min: int,
               s_t_min: int, cpu: bool = False) -> Allocation:
    """The reference optimum: the best Theta over every (c_env, E, s_sim, s_g, B_g, B_t), training taking the rest.

    Deliberately naive, to check the clever paths: every profiled (c_env, E) whose cores fit, every profiled
    s_sim of it (a quota between grid points reads the same rate and leaves less to the others), every integer
    s_g, every pair within M_gpu. ``cpu``: quotas are cores, s_sim = c_env * E, and the three stages share N
    (the :func:`allocate_cpu` setting). ``evaluations`` counts (c_env, E, s_sim, s_g) candidates.
    """
    _require_batch_pair(profiles, M_gpu)
    pairs = [(g, t) for g in profiles._gen_curves for t in profiles._train_curves if profiles.memory(g, t) <= M_gpu]
    room = N if cpu else total
    best, evaluations = None, 0
    for (c_env, E), curve in profiles._sim_curves.items():
        if c_env * E > (N - s_g_min - s_t_min if cpu else N):
            continue
        for s_sim in [c_env * E] if cpu else curve.quotas:
            T_sim = profiles.P_sim(c_env, E, s_sim)
            for s_g in range(s_g_min, room - s_sim - s_t_min + 1):
                s_t = room - s_sim - s_g
                evaluations += 1
                for B_g, B_t in pairs:
                    T_gen, T_train = profiles.P_gen(s_g, B_g), profiles.P_train(s_t, B_t)
                    value = theta(T_sim, T_gen, T_train)
                    if value > 0 and (best is None or value > best.theta):
                        best = Allocation(c_env, E, s_sim, s_g, s_t, B_g, B_t, T_sim, T_gen, T_train, value, 0,
                                          "exhaustive")
    if best is None:
        raise InfeasibleError(f"no configuration within N={N} cores and total={room} has a positive throughput")
    best.evaluations = evaluations
    return best


def predict(profiles: Profiles, alloc: Allocation) -> float:
    """Theta of ``alloc`` read from ``profiles`` with the same conservative lookups (e.g. after :func:`refine`)."""
    T_sim = profiles.P_sim(alloc.c_env, alloc.E, alloc.s_sim)
    T_gen, T_train = profiles.P_gen(alloc.s_gen, alloc.B_gen), profiles.P_train(alloc.s_train, alloc.B_train)
    if alloc.method == "shared":
        T_gen = T_train = _time_shared(T_gen, T_train)
    return theta(T_sim, T_gen, T_train)


def refine(profiles: Profiles, alloc: Allocation, measured_rollout: float, measured_train: float) -> Profiles:
    """Runtime adaptation: tables rescaled so the allocation in use predicts what was measured.

    Training: every P_train entry is scaled by measured_train / alloc.T_train, so the entry in use becomes the
    measurement. Rollout: a rollout rate cannot tell a slower simulator from a slower generator, so P_sim and
    P_gen are both scaled by measured_rollout / min(T_sim, T_gen), which keeps their ratio and makes the
    predicted T_r the measurement. Scaling whole tables assumes a stage that got 30 % slower is 30 % slower at
    every quota and batch (stage cost changed, not its scaling). Memory tables are unchanged.
    """
    predicted_rollout = min(alloc.T_sim, alloc.T_gen)
    if measured_rollout <= 0 or measured_train <= 0 or predicted_rollout <= 0 or alloc.T_train <= 0:
        raise ValueError(f"refine needs positive rates: measured {measured_rollout}, {measured_train}; "
                         f"predicted {predicted_rollout}, {alloc.T_train}")
    rollout_ratio, train_ratio = measured_rollout / predicted_rollout, measured_train / alloc.T_train
    return Profiles(
        sim={key: rate * rollout_ratio for key, rate in profiles.sim.items()},
        gen={key: rate * rollout_ratio for key, rate in profiles.gen.items()},
        train={key: rate * train_ratio for key, rate in profiles.train.items()},
        gen_mem=dict(profiles.gen_mem),
        train_mem=dict(profiles.train_mem),
        sim_cores_used=profiles.sim_cores_used,
    )
