"""Greedy core rebinding (paper, Appendix "Greedy core rebinding", Algorithm greedy-step).

Pure scheduling state, no I/O and no clock: the sim service calls
:meth:`CoreRebinding.dispatch` whenever a core may be free and
:meth:`CoreRebinding.complete` when a step finishes, passing the measured
latency. Names follow the paper: ``s_e`` completed steps of env e's current
chunk of length ``K_e``, ``E_running``, latency table ``H``.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class EnvState:
    env: int
    s: int = 0  # completed steps of the current chunk (s_e)
    K: int = 0  # length of the current chunk; s == K means no action is available
    H: float | None = None  # most recent step latency; None = never measured (scheduled first)


class CoreRebinding:
    """Assigns free cores of the simulation budget to ready environments, longest latency first."""

    def __init__(self, cores: list[int]):
        if not cores:
            raise ValueError("the simulation core budget is empty")
        self.envs: dict[int, EnvState] = {}
        self.running: dict[int, int] = {}  # E_running: env -> core it runs on
        self.budget: list[int] = list(dict.fromkeys(cores))
        self.free: list[int] = list(self.budget)

    def add_env(self, env: int) -> None:
        self.envs.setdefault(env, EnvState(env))

    def submit_chunk(self, env: int, K: int) -> None:
        """Env ``env`` received a chunk of ``K`` actions: a_{e,0..K-1} are available."""
        state = self.envs[env]
        if env in self.running or state.s < state.K:
            raise RuntimeError(f"env {env} got a new chunk before finishing its current one")
        state.s, state.K = 0, K

    def ready(self) -> list[EnvState]:
        """E_ready = {e | s_e < K_e, e not in E_running, a_{e,s_e} available} (paper, Eq. ready-env)."""
        return [e for e in self.envs.values() if e.s < e.K and e.env not in self.running]

    def dispatch(self) -> list[tuple[int, int]]:
        """For every free core with a ready env: pick argmax H (never measured first), mark it
        running, and return ``(env, core)`` pairs to bind and step. Empty ready set: cores stay idle."""
        out = []
        while self.free:
            ready = self.ready()
            if not ready:
                break
            # Selection and the running mark happen together, before anything can interleave.
            chosen = max(ready, key=lambda e: (e.H is None, e.H or 0.0))
            core = self.free.pop(0)
            self.running[chosen.env] = core
            out.append((chosen.env, core))
        return out

    def complete(self, env: int, latency: float, chunk_ended: bool = False) -> bool:
        """A step of ``env`` finished after ``latency`` seconds: advance s_e, update H, clear running,
        release the core. ``chunk_ended`` (the episode ended) drops the chunk's remaining actions.
        Returns True when the env's chunk is finished."""
        core = self.running.pop(env)
        state = self.envs[env]
        state.s = state.K if chunk_ended else state.s + 1
        state.H = latency
        if core in self.budget:
            self.free.append(core)
        return state.s >= state.K

    def set_budget(self, cores: list[int]) -> None:
        """Change the simulation core budget at run time; a removed core that is busy is
        retired when its step completes."""
        if not cores:
            raise ValueError("the simulation core budget is empty")
        self.budget = list(dict.fromkeys(cores))
        busy = set(self.running.values())
        self.free = [c for c in self.budget if c not in busy]

    @property
    def idle_cores(self) -> int:
        return len(self.free)
