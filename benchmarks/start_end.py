"""What EBRL and the one-process peer spend outside their loops: from the command to the first env step, and from
the last update to the command's exit (issue 51: each within 3 s of the peer's).

    python benchmarks/start_end.py --rounds 3                 # Warp's CPU device, the race's CPU sizes
    python benchmarks/start_end.py --rounds 3 --gpu           # the GPU race's sizes (the kit: check.sh start_end)

Each round runs, one after the other, ``ebrl up configs/mjwarp_pickcube.toml`` for 2 iterations and
``benchmarks/peers/mjwarp_ppo.py`` for 2 updates, on the same MuJoCo Warp batch of ``PandaPickCube-v0``, and times the
whole command from here (launch to exit, wall clock). Where each loop starts and ends is read from what the side
itself wrote: EBRL's recording (the first ``chunk`` span of a simulator lane; the end of training's last ``update``
span), the peer's JSON (``started_at_epoch`` + ``env_start_s``, its worlds built; the last update in its curve).
Both sides build their worlds before their first step, so world building counts as neither's overhead... except
where one builds them slower. Writes ``--json`` (default ``benchmarks/results/start_end_cpu.json``): each round's
numbers and per side the medians, and EBRL's extra seconds at each end.
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
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

sys.path.insert(0, str(ROOT / "benchmarks"))
from pickcube_race import CONFIG, CPU_PEER, CPU_SETS  # noqa: E402
from ebrl import bench  # noqa: E402
from ebrl.viz import record  # noqa: E402

ITERATIONS = 2


def timed(argv: list[str], timeout: float) -> tuple[float, float, int]:
    """Run ``argv`` in the repository; its launch and exit on the wall clock, and its exit status."""
    start = time.time()
    code = subprocess.run(argv, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                          timeout=timeout).returncode
    return start, time.time(), code


def ebrl_round(out: Path, gpu: bool, timeout: float) -> dict[str, float]:
    sets = ([] if gpu else CPU_SETS) + [f"run.iterations={ITERATIONS}", 'viz.rerun="off"', f'run.output_dir="{out}"']
    argv = [sys.executable, "-m", "ebrl.cli", "up", CONFIG]
    for item in sets:
        argv += ["--set", item]
    start, end, code = timed(argv, timeout)
    (run_dir,) = out.iterdir()
    rec = record.read(run_dir)
    first_step = min(s.start for s in rec.spans if s.lane.startswith("sim.") and s.label == "chunk")
    last_update = max(s.end for s in rec.spans if s.lane == "train" and s.label == "update")
    return {"exit_code": code, "command_s": end - start, "to_first_step_s": first_step - start,
            "after_last_update_s": end - last_update}


def peer_round(out: Path, gpu: bool, timeout: float) -> dict[str, float]:
    cpu = [] if gpu else CPU_PEER
    num_envs = int(cpu[cpu.index("--num-envs") + 1]) if cpu else 2048
    argv = [sys.executable, "benchmarks/peers/mjwarp_ppo.py", *cpu, "--total-timesteps",
            str(ITERATIONS * num_envs * 32), "--num-envs", str(num_envs), "--json", str(out)]
    start, end, code = timed(argv, timeout)
    result = json.loads(out.read_text())
    summary, curve = result["summary"], result["curve"]
    t0 = summary["started_at_epoch"]
    return {"exit_code": code, "command_s": end - start, "to_first_step_s": t0 + summary["env_start_s"] - start,
            "after_last_update_s": end - (t0 + curve[-1]["wall_s"])}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--gpu", action="store_true", help="the GPU race's sizes (default: Warp's CPU device)")
    parser.add_argument("--timeout", type=float, default=600.0, help="seconds a command may take")
    parser.add_argument("--json", default=None, help="default: benchmarks/results/start_end_{cpu,gpu}.json")
    args = parser.parse_args(argv)
    runs: dict[str, list[dict[str, float]]] = {"ebrl": [], "peer": []}
    with tempfile.TemporaryDirectory(prefix="ebrl-start-end-") as tmp:
        for r in range(args.rounds):
            runs["ebrl"].append(ebrl_round(Path(tmp) / f"ebrl{r}", args.gpu, args.timeout))
            runs["peer"].append(peer_round(Path(tmp) / f"peer{r}.json", args.gpu, args.timeout))
            print(f"round {r}: " + "; ".join(f"{side} " + ", ".join(f"{k} {v:.2f}" for k, v in rs[-1].items())
                                              for side, rs in runs.items()), flush=True)
    fields = ("command_s", "to_first_step_s", "after_last_update_s")
    medians = {side: {f: statistics.median(r[f] for r in rs) for f in fields} for side, rs in runs.items()}
    extra = {f: medians["ebrl"][f] - medians["peer"][f] for f in fields}
    out = Path(args.json or ROOT / "benchmarks" / "results" / f"start_end_{'gpu' if args.gpu else 'cpu'}.json")
    command = "python benchmarks/start_end.py " + " ".join(argv if argv is not None else sys.argv[1:])
    out.write_text(json.dumps({
        "command": command.strip(), "commit": bench.commit(),
        "machine": f"{len(os.sched_getaffinity(0))} usable cores",
        "platform": platform.machine(), "date": time.strftime("%Y-%m-%d"), "rounds": args.rounds,
        "iterations": ITERATIONS, "runs": runs, "medians": medians, "ebrl_extra_s": extra}, indent=1) + "\n")
    print(f"medians: {json.dumps(medians)}\nEBRL's extra seconds: " + ", ".join(f"{k} {v:+.2f}" for k, v in extra.items()))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
