"""Outside peer for EBRL: Sample Factory 2's own MuJoCo example on HalfCheetah, timed to a stated return.

    python benchmarks/peers/sample_factory.py --target-return 1000 --max-seconds 900 --seed 0 \
        --json benchmarks/results/peer_sample_factory.json

Sample Factory 2.1.1 (https://github.com/alex-petrenko/sample-factory) pins
``numpy<2`` and ``gymnasium<1``, so it cannot share EBRL's environment. On first
use this script creates its own virtual environment at
``benchmarks/peers/.venv-sf`` with the versions in ``PINS`` (again whenever
they change) and runs SF there; this script itself needs only the standard
library. ``torch==2.13.0`` resolves to the CPU build on the development
machine; elsewhere pip may pick the CUDA build (it works on CPU too, it is just
larger).

What runs is SF's example entry point, ``python -m sf_examples.mujoco.train_mujoco
--env=mujoco_halfcheetah``, with the example's own hyper-parameters
(``sf_examples/mujoco/mujoco_params.py``: tanh MLP 64-64, batch 1024, rollout
64, lr 2.95e-3 linearly decayed, 2 epochs x 4 minibatches, input and return
normalisation, synchronous PPO unless ``--async_rl=True``). Only what sizes it
for this machine and the measurement is set here: ``--device=cpu``,
``--num_workers`` x ``--num_envs_per_worker`` (default 2 x 4 = 8 envs, as EBRL
and the CleanRL-style peer), ``--train_for_env_steps`` (2.1.1 ignores
``--train_for_seconds``), ``--seed`` and ``--stats_avg=20`` so that SF's
"Avg episode reward" is the mean raw return of the last 20 episodes, EBRL's
``run.target_return`` rule. Arguments this script does not know go to SF
unchanged (e.g. ``--async_rl=True``).

SF's example registers gymnasium's ``HalfCheetah-v4`` (gymnasium 0.29 has no
v5). v5 changed only arguments, info keys and the minimum MuJoCo version, not
the model, the reward or the observation, so returns are comparable with
EBRL's ``HalfCheetah-v5``.

SF has no stopping rule on return. Its runner prints the frame count and the
mean return every 5 s; this script reads that log as it comes, stamps each
report with the wall clock since SF was launched (its interpreter start-up,
process spawning and env creation are counted, as EBRL's clock counts from
launch), and stops SF at the first report at or above ``--target-return``, so
the time to target is late by at most one 5 s report. SF 2.1.1 can hang on
exit waiting for its learner process, so the whole process group is
terminated, then killed.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import queue
import re
import shlex
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent.parent
VENV = HERE / ".venv-sf"
PINS = ["sample-factory[mujoco]==2.1.1", "torch==2.13.0", "numpy==1.26.4", "gymnasium==0.29.1", "mujoco==2.3.3"]
VERSIONED = ["sample-factory", "torch", "numpy", "gymnasium", "mujoco"]
ENV_NAME, ENV_ID = "mujoco_halfcheetah", "HalfCheetah-v4"  # SF's name for it and what its example makes
RETURN_WINDOW = 20

ANSI = re.compile(r"\x1b\[[0-9;]*m")
FPS = re.compile(r"Fps is \(10 sec: ([^,]+), 60 sec: ([^,]+), 300 sec: ([^)]+)\)\. Total num frames: (\d+)\.")
REWARD = re.compile(r"Avg episode reward: \[\(0, '([-\d.naif]+)'\)\]")
READY = "All inference workers are ready"
LEARNER_STOPPED = "Stopping LearnerWorker_p0"


def venv_python() -> Path:
    """SF's interpreter, after (re)creating its virtual environment when the pins changed."""
    python, stamp = VENV / "bin" / "python", VENV / "ebrl-pins.txt"
    wanted = "\n".join(PINS) + "\n"
    if python.exists() and stamp.exists() and stamp.read_text() == wanted:
        return python
    print(f"creating {VENV.relative_to(ROOT)} with {' '.join(PINS)} ...", flush=True)
    subprocess.run([sys.executable, "-m", "venv", str(VENV)], check=True)
    subprocess.run([str(python), "-m", "pip", "install", "--quiet", "--upgrade", "pip"], check=True)
    subprocess.run([str(python), "-m", "pip", "install", "--quiet", *PINS], check=True)
    stamp.write_text(wanted)
    return python


def versions(python: Path) -> dict[str, str]:
    code = ("import importlib.metadata as m, json, platform; "
            f"print(json.dumps({{'python': platform.python_version(), "
            f"**{{p: m.version(p) for p in {VERSIONED!r}}}}}))")
    return json.loads(subprocess.run([str(python), "-c", code], check=True, capture_output=True, text=True).stdout)


def number(text: str) -> float | None:
    value = float(text)
    return None if value != value else value  # SF prints nan before it has two reports


def stop_group(proc: subprocess.Popen, grace: float = 10.0) -> None:
    """SF's main process, its workers and their children share one process group (its own session)."""
    for sig in (signal.SIGTERM, signal.SIGKILL):
        try:
            os.killpg(proc.pid, sig)
        except ProcessLookupError:
            return
        try:
            proc.wait(grace)
            return
        except subprocess.TimeoutExpired:
            continue


def run(cmd: list[str], target: float | None, max_seconds: float) -> dict:
    """Run SF, follow its reports, stop it on target, time limit or its own end; return what was seen."""
    t0 = time.monotonic()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, bufsize=1,
                            start_new_session=True, env={**os.environ, "PYTHONUNBUFFERED": "1"}, cwd=ROOT)
    lines: queue.Queue[tuple[float, str | None]] = queue.Queue()

    def pump() -> None:
        for line in proc.stdout:
            lines.put((time.monotonic() - t0, ANSI.sub("", line.rstrip())))
        lines.put((time.monotonic() - t0, None))

    threading.Thread(target=pump, daemon=True).start()
    curve: list[dict] = []
    seen = {"ready_s": None, "reached": None, "stop_reason": None, "last_fps": None}
    tail: list[str] = []  # the last lines, to say why a run failed
    try:
        while seen["stop_reason"] is None:
            try:
                now, line = lines.get(timeout=1.0)
            except queue.Empty:
                now, line = time.monotonic() - t0, ""
            if line is None:
                seen["stop_reason"] = "exited"
                break
            tail = (tail + [line])[-30:]
            if READY in line and seen["ready_s"] is None:
                seen["ready_s"] = now
            elif m := FPS.search(line):
                seen["last_fps"] = {"10s": number(m[1]), "60s": number(m[2]), "300s": number(m[3])}
                curve.append({"wall_s": round(now, 2), "env_frames": int(m[4]), "fps_10s": number(m[1]),
                              "return": None})
            elif (m := REWARD.search(line)) and curve:
                ret = curve[-1]["return"] = number(m[1])
                print(f"[{now:7.1f} s] env frames {curve[-1]['env_frames']:9d}  fps (10 s) "
                      f"{curve[-1]['fps_10s'] or 0:7.0f}  return (last {RETURN_WINDOW}) {ret:.1f}", flush=True)
                if target is not None and ret is not None and ret >= target:
                    seen["reached"] = {"wall_s": round(now, 2), "env_frames": curve[-1]["env_frames"],
                                       "return": ret}
                    seen["stop_reason"] = "target_return"
            elif LEARNER_STOPPED in line:
                seen["stop_reason"] = "train_for_env_steps"
            if now >= max_seconds and seen["stop_reason"] is None:
                seen["stop_reason"] = "max_seconds"
        seen["wall_s"] = time.monotonic() - t0
    finally:
        stop_group(proc)
    if not curve:
        raise RuntimeError("Sample Factory produced no report:\n" + "\n".join(tail))
    return {"curve": curve, **seen}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0], epilog="other arguments go to Sample Factory",
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--target-return", type=lambda s: None if s.lower() == "none" else float(s), default=1000.0,
                   help="stop at the first report whose mean return (last 20 episodes) reaches this; 'none': off")
    p.add_argument("--max-seconds", type=float, default=900.0, help="wall-clock cap from SF's launch")
    p.add_argument("--train-for-env-steps", type=int, default=2_000_000, help="SF's own end")
    p.add_argument("--num-workers", type=int, default=2)
    p.add_argument("--num-envs-per-worker", type=int, default=4)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--train-dir", default="runs/peers/sample_factory")
    p.add_argument("--experiment", default="halfcheetah")
    p.add_argument("--json", default=None, help="write the summary, settings and curve here")
    args, sf_args = p.parse_known_args()

    python = venv_python()
    cmd = [str(python), "-m", "sf_examples.mujoco.train_mujoco", f"--env={ENV_NAME}",
           f"--experiment={args.experiment}", f"--train_dir={args.train_dir}", "--restart_behavior=overwrite",
           "--device=cpu", f"--num_workers={args.num_workers}", f"--num_envs_per_worker={args.num_envs_per_worker}",
           f"--train_for_env_steps={args.train_for_env_steps}", f"--stats_avg={RETURN_WINDOW}",
           f"--seed={args.seed}", *sf_args]
    print("$ " + shlex.join(cmd), flush=True)
    seen = run(cmd, args.target_return, args.max_seconds)

    wall_s, curve, reached = seen["wall_s"], seen["curve"], seen["reached"]
    frames = curve[-1]["env_frames"]
    final = next((pt["return"] for pt in reversed(curve) if pt["return"] is not None), None)
    summary = {
        "stop_reason": seen["stop_reason"],
        "wall_s": round(wall_s, 2),
        "ready_s": None if seen["ready_s"] is None else round(seen["ready_s"], 2),
        "env_frames": frames,
        "env_frames_per_s": round(frames / wall_s, 1),
        "sf_fps_last": seen["last_fps"],
        "final_return": final,
        "target_return": args.target_return,
        "target_reached": reached,
    }
    print()
    if reached:
        print(f"reached target return {args.target_return:g}: mean return {reached['return']:.1f} after "
              f"{reached['wall_s']:.1f} s wall clock ({reached['env_frames']} env frames)")
    else:
        print(f"target return {args.target_return} not reached (stopped on {seen['stop_reason']})")
    print(f"wall {wall_s:.1f} s (workers ready after {summary['ready_s']} s), env frames {frames}, "
          f"{summary['env_frames_per_s']:.0f} env frames/s from launch, SF's last fps {seen['last_fps']}, "
          f"final mean return (last {RETURN_WINDOW}) {final}")

    if args.json:
        config_path = ROOT / args.train_dir / args.experiment / "config.json"
        out = {
            "peer": "Sample Factory 2 (sf_examples.mujoco.train_mujoco), its MuJoCo defaults, CPU",
            "command": shlex.join([sys.executable, *sys.argv]),
            "sf_command": shlex.join(cmd),
            "env_id": ENV_ID,
            "machine": f"{platform.machine()}, {len(os.sched_getaffinity(0))} usable cores",
            "date": time.strftime("%Y-%m-%d"),
            "versions": versions(python),
            "summary": summary,
            "sf_config": json.loads(config_path.read_text()) if config_path.exists() else None,
            "curve": curve,
        }
        path = Path(args.json)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(out, indent=2) + "\n")
        print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
