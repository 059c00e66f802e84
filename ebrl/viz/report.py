"""``ebrl report RUN_DIR``: a static Gantt, throughput over time and a markdown summary, without a display.

Everything comes from the run's recording (``RUN_DIR/stats.msgpack``, written by
the launcher), so a report can be made at any time after (or during) a run:

* ``gantt.png`` — every lane over the window (busy spans coloured by state,
  ``wait`` in grey, gaps idle); ``gantt_zoom.png`` — the last ``ZOOM_S``
  seconds of the window, where single spans are visible;
* ``throughput.png`` — env steps/s and trajectories/s over time (sim stats);
* ``report.md`` — per lane busy, waiting and idle fractions, how much of
  training overlapped rollout, throughput per time bin, and the event log.
"""

from __future__ import annotations

import collections
import statistics
import time
from pathlib import Path
from typing import Any

from ebrl.viz import record
from ebrl.viz.timeline import STATE_COLORS, intersect, is_busy, lane_order, state_of, total, union

ZOOM_S = 10.0
BINS = 12


def _rgba(value: int) -> tuple[float, float, float, float]:
    return tuple(((value >> shift) & 0xFF) / 255 for shift in (24, 16, 8, 0))  # type: ignore[return-value]


def window_of(rec: record.Recording, start: float | None, end: float | None, last: float | None) -> tuple[float, float]:
    """Absolute (epoch) window from offsets relative to the run's first record."""
    t0, t1 = rec.bounds()
    if last is not None:
        return max(t0, t1 - last), t1
    lo = t0 + (start or 0.0)
    hi = t0 + end if end is not None else t1
    if hi <= lo:
        raise ValueError(f"empty window: start {lo - t0:.1f} s, end {hi - t0:.1f} s (the run covers {t1 - t0:.1f} s)")
    return lo, hi


def lane_table(rec: record.Recording, lo: float, hi: float) -> list[dict[str, Any]]:
    """Busy / waiting / idle fraction of every lane over ``[lo, hi]``."""
    by_lane: dict[str, list] = collections.defaultdict(list)
    for span in rec.spans:
        by_lane[span.lane].append(span)
    rows = []
    length = hi - lo
    for lane in sorted(by_lane, key=lane_order):
        spans = by_lane[lane]
        busy = union([(s.start, s.end) for s in spans if is_busy(s)], lo, hi)
        waiting = union([(s.start, s.end) for s in spans if not is_busy(s)], lo, hi)
        busy_s, wait_s = total(busy), total(waiting)
        inside = [s for s in spans if s.end > lo and s.start < hi]
        rows.append({"lane": lane, "spans": len(inside), "busy": busy_s / length, "waiting": wait_s / length,
                     "idle": max(0.0, 1.0 - (busy_s + wait_s) / length),
                     "mean_ms": 1e3 * statistics.fmean(s.end - s.start for s in inside if is_busy(s))
                     if any(is_busy(s) for s in inside) else 0.0})
    return rows


def overlap(rec: record.Recording, lo: float, hi: float) -> dict[str, float]:
    """How much training ran while rollout (any sim lane) was busy, over ``[lo, hi]``."""
    train = union([(s.start, s.end) for s in rec.spans if s.lane == "train" and is_busy(s)], lo, hi)
    sim = union([(s.start, s.end) for s in rec.spans if s.lane.startswith("sim") and is_busy(s)], lo, hi)
    both = total(intersect(train, sim))
    train_s = total(train)
    return {"train_busy_s": train_s, "sim_busy_s": total(sim), "both_s": both,
            "of_training": both / train_s if train_s else 0.0, "of_window": both / (hi - lo)}


def throughput(rec: record.Recording, lo: float, hi: float) -> list[tuple[float, float, float]]:
    """(time, env steps/s, trajectories/s) of every sim report inside the window (summed over sim instances)."""
    latest: dict[int, tuple[float, float, float]] = {}
    out = []
    for rep in rec.stats:
        if rep.service != "sim" or not lo <= rep.time <= hi:
            continue
        latest[rep.instance] = (rep.time, rep.metrics.get("sim/env_steps_per_s", 0.0),
                                rep.metrics.get("sim/segments_per_s", 0.0))
        out.append((rep.time, sum(v[1] for v in latest.values()), sum(v[2] for v in latest.values())))
    return out


def gantt(rec: record.Recording, lo: float, hi: float, path: Path, title: str) -> list[str]:
    """Draw the Gantt of ``[lo, hi]`` to ``path``; return the lanes drawn (top to bottom)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Patch

    lanes = rec.lanes
    bars: dict[tuple[str, str], list[tuple[float, float]]] = collections.defaultdict(list)
    min_width = (hi - lo) / 1500  # about one pixel: a 0.5 ms weights publish stays visible
    for span in rec.spans:
        if span.end > lo and span.start < hi:
            a, b = max(span.start, lo), min(span.end, hi)
            bars[(span.lane, state_of(span))].append((a - lo, max(b - a, min_width)))
    fig, ax = plt.subplots(figsize=(14, 0.45 * len(lanes) + 1.6), dpi=110)
    row = {lane: len(lanes) - 1 - i for i, lane in enumerate(lanes)}
    used_states = set()
    for (lane, state), xs in bars.items():
        color = _rgba(STATE_COLORS[state]) if state in STATE_COLORS else (0.5, 0.5, 0.5, 1.0)
        ax.broken_barh(xs, (row[lane] - 0.4, 0.8), facecolors=color, linewidth=0)
        used_states.add(state)
    ax.set_yticks([row[lane] for lane in lanes], lanes)
    ax.set_ylim(-0.6, len(lanes) - 0.4)
    ax.set_xlim(0, hi - lo)
    ax.set_xlabel(f"seconds from {time.strftime('%H:%M:%S', time.localtime(lo))}")
    ax.set_title(title)
    ax.grid(axis="x", alpha=0.3)
    handles = [Patch(color=_rgba(STATE_COLORS[s]) if s in STATE_COLORS else (0.5, 0.5, 0.5, 1.0), label=s)
               for s in sorted(used_states)]
    ax.legend(handles=handles, loc="upper left", bbox_to_anchor=(1.0, 1.0), frameon=False)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return lanes


def throughput_plot(points: list[tuple[float, float, float]], lo: float, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(10, 3.5), dpi=110)
    if points:
        t = [p[0] - lo for p in points]
        ax.plot(t, [p[1] for p in points], color="tab:blue", label="env steps/s")
        ax2 = ax.twinx()
        ax2.plot(t, [p[2] for p in points], color="tab:orange", label="trajectories/s")
        ax2.set_ylabel("trajectories/s", color="tab:orange")
    ax.set_xlabel("seconds")
    ax.set_ylabel("env steps/s", color="tab:blue")
    ax.set_title("throughput over time (sim stats)")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def write(run_dir: str | Path, start: float | None = None, end: float | None = None, last: float | None = None,
          out: str | Path | None = None) -> dict[str, Path]:
    """Write the report files of ``run_dir`` (window relative to the first record); return their paths."""
    run_dir = Path(run_dir)
    source = run_dir / record.FILENAME
    if not source.exists():
        raise ValueError(f"{source} not found: is {run_dir} a run directory of a run with viz.record = true?")
    rec = record.read(source)
    if not rec.spans and not rec.stats:
        raise ValueError(f"{source} holds no spans or stats")
    lo, hi = window_of(rec, start, end, last)
    t0 = rec.bounds()[0]
    out_dir = Path(out) if out else run_dir / "report"
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = {"gantt": out_dir / "gantt.png", "gantt_zoom": out_dir / "gantt_zoom.png",
             "throughput": out_dir / "throughput.png", "markdown": out_dir / "report.md"}
    run_name = rec.stats[0].run if rec.stats else run_dir.name
    lanes = gantt(rec, lo, hi, paths["gantt"], f"{run_name}: {lo - t0:.0f}-{hi - t0:.0f} s")
    zlo = max(lo, hi - ZOOM_S)
    gantt(rec, zlo, hi, paths["gantt_zoom"], f"{run_name}: last {hi - zlo:.0f} s of the window")
    points = throughput(rec, lo, hi)
    throughput_plot(points, lo, paths["throughput"])
    paths["markdown"].write_text(markdown(rec, run_name, lo, hi, t0, lanes, points, paths))
    return paths


def markdown(rec: record.Recording, run_name: str, lo: float, hi: float, t0: float, lanes: list[str],
             points: list[tuple[float, float, float]], paths: dict[str, Path]) -> str:
    lines = [f"# Run {run_name}", "",
             f"Window: {lo - t0:.1f}-{hi - t0:.1f} s after the first record ({hi - lo:.1f} s); "
             f"{len(rec.spans)} spans, {len(rec.stats)} stats reports, {len(rec.events)} events recorded"
             + (f", {rec.malformed} malformed records skipped" if rec.malformed else "") + ".", "",
             f"![Gantt]({paths['gantt'].name})", "", f"![Gantt, last {ZOOM_S:.0f} s]({paths['gantt_zoom'].name})", "",
             "## Lanes", "", "| lane | spans | busy | waiting | idle | mean busy span (ms) |", "|---|---|---|---|---|---|"]
    for row in lane_table(rec, lo, hi):
        lines.append(f"| {row['lane']} | {row['spans']} | {row['busy']:.1%} | {row['waiting']:.1%} | {row['idle']:.1%} "
                     f"| {row['mean_ms']:.1f} |")
    ov = overlap(rec, lo, hi)
    lines += ["", "## Rollout-training overlap", "",
              f"Training was busy {ov['train_busy_s']:.1f} s and simulation (any group) {ov['sim_busy_s']:.1f} s; "
              f"both at once {ov['both_s']:.1f} s: **{ov['of_training']:.0%} of training ran while rollout went on** "
              f"({ov['of_window']:.0%} of the window).", "",
              "## Throughput over time", "", f"![throughput]({paths['throughput'].name})", ""]
    if points:
        lines += ["| from (s) | to (s) | env steps/s | trajectories/s |", "|---|---|---|---|"]
        edges = [lo + (hi - lo) * i / BINS for i in range(BINS + 1)]
        for a, b in zip(edges, edges[1:]):
            inside = [p for p in points if a <= p[0] < b or (b == hi and p[0] == hi)]
            if inside:
                lines.append(f"| {a - t0:.0f} | {b - t0:.0f} | {statistics.fmean(p[1] for p in inside):,.0f} "
                             f"| {statistics.fmean(p[2] for p in inside):.2f} |")
    if rec.events:
        lines += ["", "## Events", ""]
        lines += [f"- {e.time - t0:7.1f} s  {e.service}/{e.instance} {e.kind}: {e.text}" for e in rec.events[:200]]
    return "\n".join(lines) + "\n"
