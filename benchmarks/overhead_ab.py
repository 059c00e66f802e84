"""What a change costs a workload: this checkout against another one (``--base``, a worktree of an older commit),
side by side on one machine, ``ebrl bench`` of the ebrl mode alternating between the two, round after round.

    git worktree add /tmp/base 173eecb
    python benchmarks/overhead_ab.py --base /tmp/base --config configs/quickstart.toml --duration 30 --rounds 3 \\
        --out benchmarks/results/untrusted_sim_overhead_quickstart.json

Or one checkout against itself with settings for the new side (``--base`` left out, ``--set-new``)::

    python benchmarks/overhead_ab.py --config configs/quickstart.toml --duration 30 --rounds 3 \\
        --set-new 'run.processes=[["sim","gen","train"]]' --out benchmarks/results/shared_process_quickstart_cpu.json

Each run is ``python -m ebrl.cli bench CONFIG --modes ebrl --duration D --repeat 1 --raw-seconds 0`` run from
inside the checkout it measures, with ``PYTHONPATH`` set to it (so it and its services, started from the same
interpreter, run that checkout's code and read its config; checked before each run); the base runs first in each
round. It writes both sides' runs and their medians (env steps/s,
trajectories/s, updates/s) and the ratios new / base.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
METRICS = ("env_steps_per_s", "traj_per_s", "updates_per_s")


def commit(where: Path) -> str:
    try:
        return subprocess.check_output(["git", "-C", str(where), "rev-parse", "--short", "HEAD"], text=True).strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def code_of(checkout: Path) -> Path:
    """Where ``import ebrl`` finds the package when run as :func:`bench` runs it for ``checkout``: from inside the
    checkout, so that ``python -m`` puts it first on the path (a run from this checkout would import this
    checkout's ebrl whatever ``PYTHONPATH`` says: the measurements of 80683b3 compared one checkout with itself)."""
    found = subprocess.run([sys.executable, "-c", "import ebrl; print(ebrl.__file__)"], cwd=checkout,
                           env={**os.environ, "PYTHONPATH": str(checkout)}, capture_output=True, text=True, check=True)
    return Path(found.stdout.strip()).resolve().parent


def bench(checkout: Path, config: str, duration: float, out: Path, sets: list[str] = ()) -> dict:
    """One ``ebrl bench`` of the ebrl mode with ``checkout``'s code and config (and ``sets``: overrides), run from
    inside ``checkout`` (its services start there too); its result."""
    if code_of(checkout) != (checkout / "ebrl").resolve():
        raise SystemExit(f"overhead_ab: a run from {checkout} imports ebrl from {code_of(checkout)}, not its own")
    cmd = [sys.executable, "-m", "ebrl.cli", "bench", config, "--modes", "ebrl", "--duration", str(duration),
           "--repeat", "1", "--raw-seconds", "0", "--json", str(out), *[a for kv in sets for a in ("--set", kv)]]
    subprocess.run(cmd, cwd=checkout, env={**os.environ, "PYTHONPATH": str(checkout)}, check=True, timeout=1800,
                   stdout=subprocess.DEVNULL)
    return json.loads(out.read_text())["results"]["ebrl"][0]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--base", default=str(ROOT), help="the other checkout (a git worktree of the commit "
                        "before); default: this one (then --set-new makes the difference)")
    parser.add_argument("--set-new", action="append", default=[], metavar="SECTION.KEY=VALUE",
                        help="an override for the new side's runs only")
    parser.add_argument("--config", default="configs/quickstart.toml")
    parser.add_argument("--duration", type=float, default=30.0, help="measured seconds per run")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--out", default=None, help="write the results here (JSON)")
    args = parser.parse_args()
    sides = {"base": Path(args.base).resolve(), "new": ROOT}
    runs: dict[str, list[dict]] = {"base": [], "new": []}
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(args.rounds):
            for side, checkout in sides.items():
                result = bench(checkout, args.config, args.duration, Path(tmp) / f"{side}_{r}.json",
                               args.set_new if side == "new" else [])
                runs[side].append({m: result[m] for m in METRICS})
                print(side, r, {m: round(result[m], 2) for m in METRICS}, flush=True)
    medians = {side: {m: statistics.median(run[m] for run in rs) for m in METRICS} for side, rs in runs.items()}
    out = {"command": " ".join(["python", "benchmarks/overhead_ab.py", *sys.argv[1:]]),
           "machine": f"{len(os.sched_getaffinity(0))} usable cores", "platform": platform.machine(),
           "config": args.config, "duration_s": args.duration, "rounds": args.rounds, "set_new": args.set_new,
           "commits": {side: commit(path) for side, path in sides.items()}, "runs": runs, "medians": medians,
           "ratio": {m: medians["new"][m] / medians["base"][m] for m in METRICS}}
    print(json.dumps(out["ratio"]))
    if args.out:
        Path(args.out).write_text(json.dumps(out, indent=1) + "\n")


if __name__ == "__main__":
    main()
