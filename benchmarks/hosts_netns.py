"""A run over several hosts against one host, on the same cores: hosts as Linux network namespaces joined by
their own links, the bus over TLS between them (tests/netns_hosts.py; needs root and openssl).

    python benchmarks/hosts_netns.py --rounds 3 --iterations 60
    python benchmarks/hosts_netns.py --learning --seeds 0,1 --iterations 100

Throughput (the default): the quickstart on one host, and split as a learner (gen, train) and a simulation
host (sim), interleaved for ``--rounds`` rounds so that drift of the machine hits both alike. Each run goes
``--iterations`` updates with run.target_return out of reach (a fixed length to measure, not a learning
result); its rate is training's env steps per second between the report at ``--skip`` updates and the last
(from the primary's recording, stats.msgpack). Reports the median of each and their ratio.

``--learning``: two training ranks, both on one host, and one on each of the two hosts (gloo over the trusted
link), for each seed: training's mean return against the update, the first update at ``--threshold`` and the
final return. Writes benchmarks/results/hosts_netns{,_learning}.json.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

from netns_hosts import (Namespaces, hosts_sets, namespaces_unavailable, ranks_across_hosts_config,  # noqa: E402
                         tls_files, tls_hosts_config)
from ebrl.viz import record  # noqa: E402

RESULTS = ROOT / "benchmarks" / "results"


def train_reports(out_dir: Path) -> list:
    """Training rank 0's reports from the one run directory of the primary under ``out_dir``."""
    (run_dir,) = [p for p in out_dir.iterdir() if p.is_dir()]
    return [r for r in record.read(run_dir).stats if r.service == "train" and r.instance == 0]


def rate(reports: list, skip: int) -> float:
    """Training's env steps per second from the first report at ``skip`` updates to the last."""
    window = [r for r in reports if r.metrics.get("train/policy_version", 0) >= skip and "train/env_steps" in r.metrics]
    first, last = window[0], window[-1]
    return (last.metrics["train/env_steps"] - first.metrics["train/env_steps"]) / (last.time - first.time)


def curve(reports: list) -> list[dict[str, float]]:
    return [{"policy_version": r.metrics["train/policy_version"], "env_steps": r.metrics.get("train/env_steps", 0.0),
             "return": r.metrics["train/episode_return_mean"], "time": r.time} for r in reports
            if "train/episode_return_mean" in r.metrics and "train/policy_version" in r.metrics]


def finish(runs: dict, timeout: float = 1800) -> None:
    for name, run in runs.items():
        code = run.proc.wait(timeout=timeout)
        run.join()
        if code != 0:
            raise RuntimeError(f"{name} exited with {code}:\n{run.tail()}")


def one_host(hosts: Namespaces, cfg: Path, out: Path, sets: list[str]) -> list:
    """The config on the learner's namespace alone (its bus on loopback)."""
    cmd = [sys.executable, "-m", "ebrl.cli", "up", str(cfg), *[a for s in sets for a in ("--set", s)],
           "--set", f"run.output_dir={json.dumps(str(out))}"]
    done = subprocess.run(["ip", "netns", "exec", hosts.names["learner"], *cmd], cwd=ROOT, capture_output=True,
                          text=True, env={**os.environ, "PYTHONPATH": str(ROOT)})
    if done.returncode != 0:
        raise RuntimeError(f"one host exited with {done.returncode}:\n{done.stdout[-3000:]}")
    return train_reports(out)


def throughput(args, hosts: Namespaces, files: dict, work: Path) -> dict:
    split_cfg = tls_hosts_config(work, hosts)
    common = [f"run.iterations={args.iterations}", "run.target_return=1e9"]
    rates: dict[str, list[float]] = {"one host": [], "two hosts": []}
    for rnd in range(args.rounds):
        print(f"round {rnd + 1}/{args.rounds}: one host ...", file=sys.stderr, flush=True)
        out = work / f"one-{rnd}"
        reports = one_host(hosts, ROOT / "configs" / "quickstart.toml", out,
                           [*common, 'viz.rerun="off"', "run.stats_interval=0.5", "run.name=netns"])
        rates["one host"].append(rate(reports, args.skip))
        print(f"round {rnd + 1}/{args.rounds}: two hosts ...", file=sys.stderr, flush=True)
        base = work / f"two-{rnd}"
        runs = {name: hosts.up(name, split_cfg, *common, *hosts_sets(base, name, files["learner" if name == "learner"
                                                                                      else "sim"]))
                for name in ("learner", "sim-0")}
        finish(runs)
        rates["two hosts"].append(rate(train_reports(base / "learner"), args.skip))
        print({k: [round(v) for v in vs] for k, vs in rates.items()}, file=sys.stderr, flush=True)
    one, two = statistics.median(rates["one host"]), statistics.median(rates["two hosts"])
    return {"env_steps_per_s": rates, "median_one_host": one, "median_two_hosts": two, "ratio": two / one}


def learning(args, hosts: Namespaces, files: dict, work: Path) -> dict:
    across = ranks_across_hosts_config(work, hosts)
    common = [f"run.iterations={args.iterations}", "run.target_return=1e9"]
    curves: dict[str, dict[int, list]] = {"one host": {}, "two hosts": {}}
    for seed in args.seeds:
        print(f"seed {seed}: two ranks on one host ...", file=sys.stderr, flush=True)
        curves["one host"][seed] = curve(one_host(
            hosts, ROOT / "configs" / "quickstart.toml", work / f"one-{seed}",
            [*common, f"run.seed={seed}", "train.world_size=2", 'viz.rerun="off"', "run.name=netns"]))
        print(f"seed {seed}: one rank on each of two hosts ...", file=sys.stderr, flush=True)
        base = work / f"two-{seed}"
        runs = {name: hosts.up(name, across, *common, f"run.seed={seed}",
                               *hosts_sets(base, name, files["learner" if name == "learner" else "sim"]))
                for name in ("learner", "sim-0")}
        finish(runs)
        curves["two hosts"][seed] = curve(train_reports(base / "learner"))
    summary = {}
    for where, by_seed in curves.items():
        firsts = {seed: next((int(p["policy_version"]) for p in c if p["return"] >= args.threshold), None)
                  for seed, c in by_seed.items()}
        finals = {seed: statistics.fmean(p["return"] for p in c[-5:]) for seed, c in by_seed.items()}
        summary[where] = {"first_update_at_threshold": firsts, "final_return_last5": finals}
        print(where, summary[where], file=sys.stderr, flush=True)
    return {"summary": summary, "curves": curves, "threshold": args.threshold}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--iterations", type=int, default=60)
    parser.add_argument("--skip", type=int, default=5, help="updates before the measured window (start-up)")
    parser.add_argument("--learning", action="store_true", help="two training ranks: one host against two")
    parser.add_argument("--seeds", type=lambda s: [int(x) for x in s.split(",")], default=[0, 1])
    parser.add_argument("--threshold", type=float, default=900.0)
    args = parser.parse_args()
    if why := namespaces_unavailable():
        sys.exit(f"hosts_netns: {why}")
    started, load_before = time.time(), os.getloadavg()
    hosts = Namespaces(1)
    try:
        with tempfile.TemporaryDirectory(prefix="ebrl-netns-") as tmp:
            work = Path(tmp)
            files = tls_files(work / "tls", hosts)
            result = (learning if args.learning else throughput)(args, hosts, files, work)
    finally:
        hosts.close()
    name = "hosts_netns_learning" if args.learning else "hosts_netns"
    out = {"command": " ".join(["python benchmarks/hosts_netns.py", *sys.argv[1:]]),
           "machine": {"usable_cores": len(os.sched_getaffinity(0)), "load_average_before": load_before,
                       "load_average_after": os.getloadavg()},
           "iterations": args.iterations, "wall_s": time.time() - started, **result}
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / f"{name}.json").write_text(json.dumps(out, indent=2) + "\n")
    print(json.dumps({k: v for k, v in out.items() if k != "curves"}, indent=2))


if __name__ == "__main__":
    main()
