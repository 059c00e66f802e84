"""Synthetic stage tables with random shapes, shared by the allocator's tests and its quality benchmark."""

from __future__ import annotations

import numpy as np

from ebrl.alloc.algorithm import Profiles


def random_tables(seed: int, monotone: bool) -> Profiles:
    """Random tables: gen/train ~ scale * s^alpha * B / (B + b) with +-10 % noise per entry (made monotone by a
    running maximum when ``monotone``), simulators saturating at a random knee; memory grows with batch."""
    rng = np.random.default_rng(seed)
    grid = np.arange(10, 101, 10)

    def curve(B: int, alpha_range: tuple[float, float]) -> np.ndarray:
        rate = rng.uniform(50, 150) * B / (B + rng.uniform(4, 32)) * (grid / 100) ** rng.uniform(*alpha_range)
        rate = rate * (1 + rng.uniform(-0.1, 0.1, len(grid)))
        return np.maximum.accumulate(rate) if monotone else rate

    gen, train = {}, {}
    for B in (8, 16, 32):
        gen.update({(int(s), B): float(r) for s, r in zip(grid, curve(B, (0.5, 1.2)))})
        train.update({(int(s), B): float(r) for s, r in zip(grid, curve(B, (0.7, 1.1)))})
    cap, knee = rng.uniform(20, 120), rng.choice([20, 30, 40])
    sim = {}
    for c_env in (1, 2):
        for E in (4, 8):
            top, sharpness = cap * E / 8 * rng.uniform(0.7, 1.3), rng.uniform(0.5, 2.0)
            sim.update({(c_env, E, s): float(top * min(1.0, s / knee) ** sharpness) for s in range(10, 60, 10)})
    return Profiles(sim, gen, train, gen_mem={8: 8.0, 16: 16.0, 32: 32.0}, train_mem={8: 16.0, 16: 32.0, 32: 64.0})
