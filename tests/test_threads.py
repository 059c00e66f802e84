"""torch's thread count reaches the worker thread that does a service's torch work (ebrl.threads)."""

from __future__ import annotations

import ctypes
import os
import subprocess
import sys
import textwrap

import helpers
import pytest
import torch

from ebrl import threads


def openmp() -> ctypes.CDLL:
    """The OpenMP runtime torch loaded (its per-thread count is what MKL's vector math uses)."""
    paths = sorted({line.split()[-1] for line in open("/proc/self/maps") if "gomp" in line.split("/")[-1]})
    if not paths:
        pytest.skip("this torch build does not use GNU OpenMP")
    return ctypes.CDLL(paths[0])


@pytest.fixture
def restore_threads():
    before = torch.get_num_threads()
    yield
    threads.set_threads(before)


def test_a_torch_pool_thread_runs_with_the_process_count_and_follows_a_change(restore_threads):
    omp = openmp()
    threads.set_threads(1)
    pool = threads.TorchPool("test-torch")
    try:
        assert pool.submit(omp.omp_get_max_threads).result() == 1
        threads.set_threads(2)  # e.g. the allocator's new quota, set on the service's main thread
        assert pool.submit(omp.omp_get_max_threads).result() == 2
        assert threads.wanted() == 2
    finally:
        pool.shutdown()


def test_a_plain_worker_thread_would_not_get_it():
    """Why TorchPool exists: in a fresh process on every core, the count set on the main thread does not reach a
    plain worker thread (it keeps OpenMP's default, one thread per core)."""
    openmp()
    cores = os.cpu_count() or 1  # the child runs on all of them (an earlier test may have pinned this process)
    if cores < 2:
        pytest.skip("OpenMP's default is one thread on one core")
    script = textwrap.dedent(f"""
        import os
        os.sched_setaffinity(0, range({cores}))
        import concurrent.futures, ctypes, torch
        from ebrl import threads
        omp = ctypes.CDLL({openmp()._name!r})
        threads.set_threads(1)
        plain = concurrent.futures.ThreadPoolExecutor(1).submit(omp.omp_get_max_threads).result()
        pooled = threads.TorchPool("t").submit(omp.omp_get_max_threads).result()
        print(omp.omp_get_max_threads(), plain, pooled)
    """)
    env = {k: v for k, v in os.environ.items() if k not in ("OMP_NUM_THREADS", "MKL_NUM_THREADS")}
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120, env=env,
                         cwd=helpers.ROOT)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["1", str(cores), "1"]


def test_a_torch_pool_passes_arguments_and_errors_through():
    pool = threads.TorchPool("test-torch")
    try:
        assert pool.submit(lambda a, b=0: a + b, 2, b=3).result() == 5
        with pytest.raises(ZeroDivisionError):
            pool.submit(lambda: 1 / 0).result()
    finally:
        pool.shutdown()


def test_a_thread_count_below_one_is_refused():
    with pytest.raises(ValueError, match="torch threads"):
        threads.set_threads(0)


def test_pool_only_keeps_the_calling_thread_at_one_and_gives_the_pool_the_count(restore_threads):
    omp = openmp()
    threads.set_threads(2, pool_only=True)  # what a service does: its event loop's thread keeps one
    pool = threads.TorchPool("test-torch")
    try:
        assert omp.omp_get_max_threads() == 1 and torch.get_num_threads() == 1
        assert pool.submit(omp.omp_get_max_threads).result() == 2 and threads.wanted() == 2
    finally:
        pool.shutdown()
