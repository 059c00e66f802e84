"""Lanes, states and interval arithmetic over spans: shared by the rerun bridge and the static report.

A lane is a row of the Gantt (``sim.g0``, ``gen``, ``train``, ``weights``,
``alloc``). A span's *state* is the kind of work it shows, which gives its
colour; ``wait`` spans are time a stage spent waiting (drawn, not busy).
"""

from __future__ import annotations

import numpy as np

from ebrl.messages import Span

STAGE_ORDER = ("sim", "gen", "train", "weights", "alloc")

# state -> RGBA; a label not listed here keeps the viewer's own colour.
STATE_COLORS: dict[str, int] = {
    "chunk": 0x4C8BF5FF,  # simulation of an action chunk
    "step": 0x4C8BF5FF,
    "wait": 0x9E9E9EFF,  # a group waiting for its actions (not busy)
    "forward": 0xF5A623FF,  # generation: a batched policy forward pass
    "update": 0x43A047FF,  # training: one PPO update
    "publish": 0x8E24AAFF,  # weights published
    "realloc": 0xE53935FF,  # allocator: a re-allocation applied
    "profile": 0xFDD835FF,
    "checkpoint": 0x6D4C41FF,  # training: a checkpoint written
}
IDLE_STATES = ("wait",)


def lane_order(lane: str) -> tuple[int, str, int, str]:
    """Sort key of a lane: stages in pipeline order (sim groups by number), then anything else."""
    stage, _, rest = lane.partition(".")
    rank = STAGE_ORDER.index(stage) if stage in STAGE_ORDER else len(STAGE_ORDER)
    digits = "".join(c for c in rest if c.isdigit())
    return rank, stage if rank == len(STAGE_ORDER) else "", int(digits) if digits else -1, lane


def state_of(span: Span) -> str:
    """The span's state: its label when it is a known kind of work; weights spans (``v<n>``) are ``publish``."""
    if span.label in STATE_COLORS:
        return span.label
    if span.lane == "weights":
        return "publish"
    return span.label


def is_busy(span: Span) -> bool:
    return state_of(span) not in IDLE_STATES


def union(intervals: list[tuple[float, float]], lo: float = -np.inf, hi: float = np.inf) -> list[tuple[float, float]]:
    """Merge overlapping ``(start, end)`` intervals, clipped to ``[lo, hi]``."""
    out: list[list[float]] = []
    for start, end in sorted(intervals):
        start, end = max(start, lo), min(end, hi)
        if end <= start:
            continue
        if out and start <= out[-1][1]:
            out[-1][1] = max(out[-1][1], end)
        else:
            out.append([start, end])
    return [(a, b) for a, b in out]


def total(intervals: list[tuple[float, float]]) -> float:
    return float(sum(b - a for a, b in intervals))


def intersect(a: list[tuple[float, float]], b: list[tuple[float, float]]) -> list[tuple[float, float]]:
    """Intersection of two merged, sorted interval lists."""
    out, i, j = [], 0, 0
    while i < len(a) and j < len(b):
        lo, hi = max(a[i][0], b[j][0]), min(a[i][1], b[j][1])
        if lo < hi:
            out.append((lo, hi))
        if a[i][1] < b[j][1]:
            i += 1
        else:
            j += 1
    return out
