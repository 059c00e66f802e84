"""``ebrl report RUN_DIR``: a static Gantt, throughput over time and a markdown summary, without a display.

Everything comes from the run's recording (``RUN_DIR/stats.msgpack``, written by
the launcher), so a report can be made at any time after (or during) a run:

* ``gantt.png`` — every lane over the window (busy spans coloured by state,
  ``wait`` in grey, gaps idle); ``gantt_zoom.png`` — the last ``ZOOM_S``
  seconds of the window, where single spans are visible;
* ``throughput.png`` — env steps/s and trajectories/s over time (sim stats);
* ``learning.png`` — learning curves against env steps and against wall-clock time: every episode's return
  with the 20-episode mean, training success, evaluated success with its 95 % interval and evaluated return
  (when the run had an eval service), and the losses (the same points the tracking sinks write,
  ``ebrl.tracking.curves``);
* ``report.md`` — per lane busy, waiting and idle fractions, how much of
  training overlapped rollout, throughput per time bin, and the event log.
"""

from __future__ import annotations

import collections
import statistics
import time
from pathlib import Path
from typing import Any

from ebrl.messages import StatsReport
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


def pyplot() -> Any:
    """matplotlib's pyplot, drawing off-screen (Agg). Importing it is most of a report's first 0.4 s on 2 cores:
    the launcher imports it on a thread while the services stop (:func:`warm_up`)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def warm_up() -> None:
    """Import what drawing needs, so that the report after the services stop takes that much less."""
    pyplot()
    import matplotlib.patches  # noqa: F401


def gantt(rec: record.Recording, lo: float, hi: float, path: Path, title: str) -> list[str]:
    """Draw the Gantt of ``[lo, hi]`` to ``path``; return the lanes drawn (top to bottom)."""
    plt = pyplot()
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
    plt = pyplot()

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


def learning_curves(rec: record.Recording) -> dict[str, list]:
    """The tracked points of the recording, per key (env steps as the log service counts them)."""
    from ebrl import tracking

    messages = sorted([*rec.stats, *rec.episodes],
                      key=lambda m: m.time if isinstance(m, StatsReport) else max(m.end_time, default=0.0))
    return tracking.curves(messages)


# (panel title, [(key, label, colour)]) of learning.png, top to bottom
LEARNING_PANELS = (
    # training's numbers (returns it computed from the rewards it received), the simulators' own word beside them
    ("return", [("train/episode_return_mean", "training: mean of the last 20 episodes", "tab:blue"),
                ("sim/episode_return_mean", "as the simulators report it", "tab:gray"),
                ("eval/return", "evaluated (deterministic)", "tab:red")]),
    ("success rate", [("train/success_rate", "training (last 20 episodes)", "tab:blue"),
                      ("sim/success_rate", "as the simulators report it", "tab:gray"),
                      ("eval/success_rate", "evaluated, 95 % interval", "tab:red")]),
    ("value loss", [("train/value_loss", "value loss", "tab:green")]),
    ("policy loss and KL", [("train/policy_loss", "policy loss", "tab:purple"),
                            ("train/approx_kl", "approx. KL (right axis)", "tab:orange")]),
)
RIGHT_AXIS = ("train/approx_kl",)  # drawn on a second y axis of its panel (another scale)


def learning_plot(series: dict[str, list], t0: float, path: Path, title: str) -> bool:
    """Draw ``learning.png``: the panels against env steps (left) and wall-clock seconds (right); False when the
    recording has no learning curve at all (nothing drawn)."""
    wanted = {key for _, lines in LEARNING_PANELS for key, _, _ in lines} | {"episode/return"}
    if not any(series.get(key) for key in wanted):
        return False
    plt = pyplot()

    fig, axes = plt.subplots(len(LEARNING_PANELS), 2, figsize=(14, 3.3 * len(LEARNING_PANELS)), dpi=100,
                             squeeze=False)
    for column, (axis_name, x_of) in enumerate((("env steps", lambda p: p.step),
                                                ("wall-clock seconds", lambda p: p.wall_time - t0))):
        for row, (panel, lines) in enumerate(LEARNING_PANELS):
            ax = axes[row][column]
            if panel == "return" and series.get("episode/return"):
                eps = series["episode/return"]
                ax.scatter([x_of(p) for p in eps], [p.value for p in eps], s=4, alpha=0.25, color="tab:gray",
                           linewidths=0, label="each episode (the simulators' word)")
            if panel == "success rate" and series.get("episode/success"):
                ax.set_ylim(-0.05, 1.05)
            handles = []
            for key, label, colour in lines:
                points = series.get(key, [])
                if not points:
                    continue
                xs, ys = [x_of(p) for p in points], [p.value for p in points]
                if key.startswith("eval/"):
                    handles += ax.plot(xs, ys, "o-", color=colour, label=label, markersize=4)
                    lo, hi = series.get(f"{key}_lo", []), series.get(f"{key}_hi", [])
                    if lo and hi and len(lo) == len(hi) == len(points):
                        ax.fill_between(xs, [p.value for p in lo], [p.value for p in hi], color=colour, alpha=0.2)
                elif key in RIGHT_AXIS:
                    right = ax.twinx()
                    handles += right.plot(xs, ys, color=colour, label=label, linewidth=1)
                    right.tick_params(axis="y", colors=colour)
                else:
                    handles += ax.plot(xs, ys, color=colour, label=label, linewidth=1.3)
            if panel == "value loss" and all(p.value > 0 for p in series.get("train/value_loss", [])):
                ax.set_yscale("log")
            ax.set_title(f"{panel} vs {axis_name}", fontsize=10)
            ax.set_xlabel(axis_name)
            ax.grid(alpha=0.3)
            if ax.has_data():
                scatter = [h for h in ax.collections if h.get_label().startswith("each episode")]
                ax.legend(handles=scatter + handles, fontsize=8, loc="best")
            else:
                ax.text(0.5, 0.5, "not recorded", ha="center", va="center", transform=ax.transAxes, color="gray")
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return True


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
    series = learning_curves(rec)  # the whole run: a learning curve is not cut to the window
    paths["learning"] = out_dir / "learning.png"
    if not learning_plot(series, t0, paths["learning"], f"{run_name}: learning curves"):
        del paths["learning"]
    paths["markdown"].write_text(markdown(rec, run_name, lo, hi, t0, lanes, points, paths, series))
    return paths


def learning_markdown(series: dict[str, list], paths: dict[str, Path]) -> list[str]:
    """The "Learning" section: the curves, the episodes' returns and every evaluation."""
    lines = ["## Learning", ""]
    if "learning" in paths:
        lines += [f"![learning curves]({paths['learning'].name})", ""]
    episodes = series.get("episode/return", [])
    if episodes:
        last = episodes[-20:]
        lines.append(f"{len(episodes)} episodes recorded over {episodes[-1].step:,} env steps; the last "
                     f"{len(last)} returned {statistics.fmean(p.value for p in last):.1f} on average "
                     f"(best episode {max(p.value for p in episodes):.1f}).")
        success = series.get("episode/success", [])
        if success:
            tail = success[-20:]
            lines.append(f"Training success over the last {len(tail)} episodes: "
                         f"{statistics.fmean(p.value for p in tail):.0%}.")
        lines.append("")
    evals = series.get("eval/success_rate", []) or series.get("eval/return", [])
    if evals:
        def at(key: str, step: int) -> str:
            found = [p.value for p in series.get(key, []) if p.step == step]
            return f"{found[-1]:.3g}" if found else "-"

        lines += ["| policy version | env steps | success | 95 % interval | return | episode length |",
                  "|---|---|---|---|---|---|"]
        for p in evals:
            lines.append(f"| {at('eval/version', p.step)} | {p.step:,} | {at('eval/success_rate', p.step)} "
                         f"| {at('eval/success_rate_lo', p.step)} - {at('eval/success_rate_hi', p.step)} "
                         f"| {at('eval/return', p.step)} | {at('eval/episode_length', p.step)} |")
        lines.append("")
    if len(lines) == 2:
        lines += ["No learning curve recorded (no episode ended and no training or eval stats).", ""]
    return lines


# What a run dropped, clipped or refused rather than learn from or crash on (issue 34), as the report lists it
DATA_HEALTH = {
    "sim/rewards_clipped": "env rewards beyond env.max_abs_reward, clipped",
    "sim/rewards_nonfinite": "env rewards that were not finite, taken as 0",
    "sim/obs_nonfinite": "env observations that were not finite (the episode ended there)",
    "train/reward_bound_dropped": "segments with rewards no sim sends, dropped",
    "train/updates_skipped": "gradient steps skipped (loss or gradient not finite)",
    "train/decisions_dropped": "decisions dropped from training (their numbers not finite)",
    "train/weights_refused": "updates whose weights were not finite, undone",
    "train/checkpoints_refused": "checkpoints not written (state not finite)",
    "train/future_version_dropped": "segments acted by a version train never made, dropped",
    "train/episode_values_refused": "segments whose episode return or length is not what their rewards and steps "
                                    "make, refused (training computes returns itself)",
    "train/segments_replayed": "segments repeating an episode's steps train already had, refused",
    "train/episodes_incomplete": "episodes not counted in the return: a segment of theirs missing or refused",
    "train/episodes_past_bound": "episodes not counted in the return: a reward past env.reward_bound "
                                 "(train/reward_bound)",
    "gen/version_resets": "times gen found itself ahead of train and went back to train's newest",
    "gen/obs_dropped": "observations whose shape does not fit the policy, dropped",
    "gen/weights_refused": "weight versions refused",
    "bus/malformed": "messages that failed validation, dropped (every service)",
    "bus/oversized": "messages past their key's size bound, dropped before decoding (every service)",
    "launcher/unknown_instances": "liveliness tokens of instances the run does not have, stopped at the "
                                  "launcher's router",
    "gen/unknown_instances": "liveliness tokens of simulators the run does not have (a mesh), not counted as hosts",
}


def data_health(rec: record.Recording) -> list[str]:
    """The "Dropped or changed data" section: each counter of ``DATA_HEALTH`` at the end of the run, summed over
    the services that report it; only those above 0."""
    latest: dict[tuple[str, int, str], float] = {}
    for report in rec.stats:
        for name in DATA_HEALTH:
            value = report.metrics.get(name)
            if value is not None:
                latest[(report.service, report.instance, name)] = value
    totals = {name: sum(v for (_, _, n), v in latest.items() if n == name) for name in DATA_HEALTH}
    rows = [f"| `{name}` | {total:,.0f} | {DATA_HEALTH[name]} |" for name, total in totals.items() if total > 0]
    lines = ["## Dropped or changed data", ""]
    if not rows:
        return lines + ["Nothing was dropped, clipped or refused.", ""]
    return lines + ["| counter | total | what |", "|---|---|---|", *rows, ""]


def markdown(rec: record.Recording, run_name: str, lo: float, hi: float, t0: float, lanes: list[str],
             points: list[tuple[float, float, float]], paths: dict[str, Path],
             series: dict[str, list] | None = None) -> str:
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
    lines += [""] + learning_markdown(series or {}, paths) + data_health(rec)
    if rec.events:
        lines += ["", "## Events", ""]
        lines += [f"- {e.time - t0:7.1f} s  {e.service}/{e.instance} {e.kind}: {e.text}" for e in rec.events[:200]]
    return "\n".join(lines) + "\n"
