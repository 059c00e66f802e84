"""torch's CPU thread count, applied in the thread that does the work.

Under OpenMP (torch's CPU builds), ``torch.set_num_threads`` sets the count of the *calling* OS thread: OpenMP's
and MKL's settings are per thread. A service that sets it on its main thread and runs its forward passes or
updates on a worker thread leaves that worker on OpenMP's default of one thread per core. MKL's vector math
(``tanh`` over a batch of 4 to 16 observations) then starts a team of threads on every call, and the team
spins between calls on the cores the simulators need. Measured on 2 cores, a 64x64 MLP's forward pass of 4
observations on a worker thread cost 6.6 ms of CPU this way instead of 0.75 ms
(``python benchmarks/torch_threads.py``, BENCHMARKS.md).

``set_threads(n)`` is the process's count (the config's ``gen.threads`` / ``train.threads``, or the allocator's
quota); ``TorchPool`` is the one-thread executor for torch work, whose tasks run with that count, also after
the allocator changes it.

A service calls it with ``pool_only=True``: its own thread (the event loop's) then keeps one torch thread and
only the pool's work runs on ``n``. Under GNU OpenMP, once a thread has run a parallel region of two or more
threads (a model's initialisation does), every team a pool thread starts afterwards runs slower: measured on 2
cores, a 256 x 256 x 256 matrix product took 266 us on a pool thread's two threads after the main thread had
used two, and 185 us where it had kept one (one thread: 335 us); SAC's gradient step on two threads went from
11.8 ms to 7.8 ms (``python benchmarks/torch_threads.py --pool-teams``, ``python benchmarks/sac_step.py``).
"""

from __future__ import annotations

import concurrent.futures
import threading
from typing import Any, Callable

_wanted = 0  # the process's count; 0: never set (each thread keeps torch's default)
_here = threading.local()  # the count this OS thread last applied


def set_threads(n: int, pool_only: bool = False) -> None:
    """Make ``n`` the process's torch thread count: in a ``TorchPool`` thread before its next task, and now in this
    thread (``pool_only``: this thread keeps one, see the module's docstring)."""
    global _wanted
    if n < 1:
        raise ValueError(f"torch threads must be >= 1, not {n}")
    import torch

    _wanted = n
    here = 1 if pool_only else n
    torch.set_num_threads(here)
    _here.n = here


def wanted() -> int:
    """The process's count (0: never set)."""
    return _wanted


def apply() -> None:
    """Apply the process's count in the calling thread, if it has not got it yet (cheap when it has)."""
    n = _wanted
    if n and getattr(_here, "n", 0) != n:
        import torch

        torch.set_num_threads(n)
        _here.n = n


def _with_threads(fn: Callable[..., Any], args: tuple, kwargs: dict) -> Any:
    apply()
    return fn(*args, **kwargs)


class TorchPool(concurrent.futures.ThreadPoolExecutor):
    """One worker thread for a service's torch work (gen's forward passes, train's updates), run with the
    process's torch thread count (``set_threads``). ``loop.run_in_executor(pool, fn, ...)`` uses it as any
    executor."""

    def __init__(self, name: str):
        super().__init__(1, thread_name_prefix=name)

    def submit(self, fn: Callable[..., Any], /, *args: Any, **kwargs: Any) -> concurrent.futures.Future:
        return super().submit(_with_threads, fn, args, kwargs)
