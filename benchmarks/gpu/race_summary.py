"""The GPU race's verdict (issue 51): from what ``check.sh mjwarp_race`` left in its results folder, each side's
seconds to 90 % success per seed, their medians and ratio.

    python benchmarks/gpu/race_summary.py RESULTS_DIR --seeds "0 1 2" [--json OUT]

Reads, per seed S: ``times.txt`` (lines ``SIDE S SECONDS``: the whole command's wall clock, from launching it to
its exit, as check.sh measured it), EBRL's ``mjwarp-race-sS/*/summary.json`` (``target_reached.wall_s``: in the
run's own clock; ``env_steps_per_s``) and the peer's ``peer_mjwarp_ppo_sS.json`` (``summary.target_reached.wall_s``,
``rollout_env_steps_per_s``). A side that did not reach 90 % has no time for that seed (shown as ``-``, and a
median over fewer seeds is said). Sides: ``ebrl`` (the config as it is: ``run.processes = "auto"``) and, where
``mjwarp_race_separate`` ran, ``ebrl_separate`` (every service a process of its own).

The acceptance it prints: EBRL's median whole command to 90 % at most 0.75x the peer's; EBRL's env steps/s while
training at least 0.9x the peer's rollout-only rate.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path

WHOLE_RATIO = 0.75  # EBRL's median whole command to 90 %, against the peer's: at most this
RATE_RATIO = 0.9  # EBRL's env steps/s while training, against the peer's rollout-only rate: at least this


def read_times(results: Path) -> dict[tuple[str, str], float]:
    """``times.txt``: (side, seed) -> the whole command's seconds."""
    out: dict[tuple[str, str], float] = {}
    path = results / "times.txt"
    for line in path.read_text().splitlines() if path.exists() else []:
        parts = line.split()
        if len(parts) == 3:
            out[(parts[0], parts[1])] = float(parts[2])
    return out


def ebrl_run(results: Path, side: str, seed: str) -> dict | None:
    """The summary.json of EBRL's run for ``seed`` (``side`` ebrl or ebrl_separate), or None."""
    folder = results / (f"mjwarp-race-s{seed}" if side == "ebrl" else f"mjwarp-race-separate-s{seed}")
    found = sorted(folder.glob("*/summary.json"))
    return json.loads(found[-1].read_text()) if found else None


def peer_run(results: Path, seed: str) -> dict | None:
    path = results / f"peer_mjwarp_ppo_s{seed}.json"
    return json.loads(path.read_text())["summary"] if path.exists() else None


def side_rows(results: Path, seeds: list[str], times: dict[tuple[str, str], float]) -> dict[str, list[dict]]:
    """Per side, per seed: in_run (seconds to 90 % in its own clock), whole (the command's seconds, when it reached
    90 %: it ends there), rate (env steps/s: EBRL's while training, the peer's in rollouts)."""
    rows: dict[str, list[dict]] = {}
    for side in ("ebrl", "ebrl_separate", "peer"):
        for seed in seeds:
            run = peer_run(results, seed) if side == "peer" else ebrl_run(results, side, seed)
            if run is None:
                continue
            reached = run.get("target_reached")
            rows.setdefault(side, []).append({
                "seed": seed, "in_run": reached["wall_s"] if reached else None,
                "whole": times.get((side, seed)) if reached else None,
                "rate": run.get("rollout_env_steps_per_s") if side == "peer" else run.get("env_steps_per_s")})
    return rows


def median(values: list[float | None]) -> float | None:
    known = [v for v in values if v is not None]
    return statistics.median(known) if known else None


def verdict(rows: dict[str, list[dict]]) -> dict:
    """Medians per side and the two ratios against the peer, with whether each acceptance holds."""
    medians = {side: {key: median([r[key] for r in side_rows]) for key in ("in_run", "whole", "rate")}
               | {"reached": sum(r["whole"] is not None for r in side_rows), "seeds": len(side_rows)}
               for side, side_rows in rows.items()}
    out: dict = {"medians": medians}
    peer = medians.get("peer", {})
    for side in ("ebrl", "ebrl_separate"):
        mine = medians.get(side)
        if not mine or not peer:
            continue
        whole = mine["whole"] / peer["whole"] if mine["whole"] and peer["whole"] else None
        rate = mine["rate"] / peer["rate"] if mine["rate"] and peer["rate"] else None
        out[side] = {"whole_ratio": whole, "rate_ratio": rate,
                     "whole_holds": whole is not None and whole <= WHOLE_RATIO,
                     "rate_holds": rate is not None and rate >= RATE_RATIO}
    return out


def shown(value: float | None, digits: int = 1) -> str:
    return "-" if value is None else f"{value:,.{digits}f}"


def report(rows: dict[str, list[dict]], result: dict) -> str:
    lines = ["| side | seed | 90 % in the run (s) | whole command (s) | env steps/s |", "|---|---|---|---|---|"]
    for side, side_rows in rows.items():
        for r in side_rows:
            lines.append(f"| {side} | {r['seed']} | {shown(r['in_run'])} | {shown(r['whole'])} | {shown(r['rate'], 0)} |")
    for side, m in result["medians"].items():
        lines.append(f"median {side}: 90 % in the run {shown(m['in_run'])} s, whole command {shown(m['whole'])} s "
                     f"({m['reached']} of {m['seeds']} seeds reached 90 %), {shown(m['rate'], 0)} env steps/s")
    for side in ("ebrl", "ebrl_separate"):
        if side in result:
            r = result[side]
            lines.append(f"{side} / peer: whole command {shown(r['whole_ratio'], 3)}x (acceptance <= {WHOLE_RATIO}: "
                         f"{'holds' if r['whole_holds'] else 'does not hold'}), env steps/s {shown(r['rate_ratio'], 3)}x "
                         f"(acceptance >= {RATE_RATIO}: {'holds' if r['rate_holds'] else 'does not hold'})")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("results", help="check.sh's results folder (/tmp/ebrl-gpu-results)")
    parser.add_argument("--seeds", default="0", help='the seeds raced, as SEEDS ("0 1 2")')
    parser.add_argument("--json", default=None, help="also write the rows and the verdict here")
    args = parser.parse_args(argv)
    results = Path(args.results)
    rows = side_rows(results, args.seeds.split(), read_times(results))
    result = verdict(rows)
    print(report(rows, result))
    if args.json:
        Path(args.json).write_text(json.dumps({"rows": rows, **result}, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
