"""``ebrl bench``: the same workload in several modes, interleaved, measured from the stats stream.

Each measurement is a real ``ebrl up`` run (a subprocess with its own bus port):
after every service is live and the first policy update is published, the
bench process reads ``ebrl/stats/<run>/**`` for ``--duration`` seconds (or until
``--trajectories`` more segments are done) and takes the difference of the
counters between the first and last report of the window. Modes run
A B C D A B C D ... so that machine drift hits all alike. ``--ablations`` adds
ebrl with each mechanism flipped (``ablation_variants``).
"""

from __future__ import annotations

import json
import os
import signal
import socket
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import msgpack
import zenoh

from ebrl import config as config_mod

BASELINES = ("colocated", "hybrid", "async")
# The mechanisms ``--ablations`` switches, each by its config key. A variant flips one of them from what the
# ebrl mode runs with this config: ``ebrl-no_<name>`` switches it off, ``ebrl+<name>`` on where the config
# leaves it off (the allocator is off by default, so its variant is usually ``ebrl+allocator``).
MECHANISMS = {
    "allocator": "alloc.enabled",
    "group_pipeline": "sim.group_pipeline",
    "overlap": "train.overlap",
    "core_rebinding": "sim.core_rebinding",
}


def base_mode(variant: str) -> str:
    """The ``run.mode`` of a variant name: ``ebrl-no_overlap`` and ``ebrl+allocator`` run mode ebrl."""
    return variant.replace("+", "-").split("-")[0]


def ablation_variants(config: str, overrides: list[str]) -> dict[str, list[str]]:
    """ebrl with each mechanism flipped from what it runs with under ``config``: variant name -> overrides."""
    from ebrl.sched.modes import resolve

    cfg = config_mod.load(config, [*overrides, "run.mode=ebrl"])
    schedule = resolve(cfg)
    running = {
        "allocator": cfg.alloc.enabled,
        "group_pipeline": schedule.groups > 1,
        "overlap": schedule.overlap,
        "core_rebinding": schedule.core_rebinding,
    }
    out = {}
    for name, key in MECHANISMS.items():
        if running[name]:
            out[f"ebrl-no_{name}"] = [f"{key}=false"]
        else:
            out[f"ebrl+{name}"] = [f"{key}=true"]
    return out


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


class StatsWindow:
    """Collects every stats report of one run (thread-safe; filled by a Zenoh callback)."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.reports: list[tuple[str, dict[str, Any]]] = []

    def on_sample(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr).split("/", 3)[3]
        if key.startswith(("spans/", "events/")):  # timeline spans and the event log are not stats
            return
        try:
            report = msgpack.unpackb(sample.payload.to_bytes())
        except Exception:
            return
        with self.lock:
            self.reports.append((key, report))

    def latest(self, source: str, name: str) -> float | None:
        with self.lock:
            for key, report in reversed(self.reports):
                if key == source and name in report["metrics"]:
                    return report["metrics"][name]
        return None

    def latest_report(self, source: str, name: str) -> tuple[float, float] | None:
        """(report time, value) of the newest report of ``source`` that has ``name``."""
        with self.lock:
            for key, report in reversed(self.reports):
                if key == source and name in report["metrics"]:
                    return report["time"], report["metrics"][name]
        return None

    def between(self, t0: float, t1: float) -> dict[str, list[dict[str, Any]]]:
        with self.lock:
            out: dict[str, list[dict[str, Any]]] = {}
            for key, report in self.reports:
                if t0 <= report["time"] <= t1:
                    out.setdefault(key, []).append(report)
            return out


def launch(config: str, name: str, overrides: list[str], out_dir: str) -> tuple[subprocess.Popen, zenoh.Config]:
    """Start ``ebrl up config`` as run ``name`` on a free loopback port; return the process and a
    Zenoh config that connects to its bus."""
    port = _free_port()
    cmd = [sys.executable, "-m", "ebrl.cli", "up", config, "--set", f"run.name={name}",
           "--set", f"run.output_dir={json.dumps(out_dir)}", "--set", f'bus.listen=["tcp/127.0.0.1:{port}"]',
           "--set", "run.stats_interval=1.0", "--set", "viz.report=false"]
    for item in overrides:
        cmd += ["--set", item]
    conf = zenoh.Config()
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("connect/endpoints", f'["tcp/127.0.0.1:{port}"]')
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True), conf


def measure(config: str, mode: str, extra: list[str], duration: float, startup_timeout: float = 300.0,
            out_dir: str = "runs/bench", trajectories: int = 0, max_seconds: float = 3600.0) -> dict[str, Any]:
    """One run of ``config`` in ``mode`` (a mode or a variant name): throughput and latencies over
    ``duration`` seconds after warm-up or, with ``trajectories`` > 0, until that many more trajectory
    segments are done (at most ``max_seconds``)."""
    name = f"bench-{mode}".replace("_", "-").replace("+", "-with-")[:40]
    proc, conf = launch(config, name, [f"run.mode={base_mode(mode)}", "run.iterations=0", *extra], out_dir)
    window = StatsWindow()

    def wait(done: Any, timeout: float, what: str) -> None:
        deadline = time.monotonic() + timeout
        while not done():
            if proc.poll() is not None:
                raise RuntimeError(f"{mode}: the run ended (exit {proc.returncode}) {what}:\n{proc.stdout.read()}")
            if time.monotonic() > deadline:
                raise RuntimeError(f"{mode}: no result after {timeout:.0f} s {what}")
            time.sleep(0.2)

    try:
        with zenoh.open(conf) as session:
            session.declare_subscriber(f"ebrl/stats/{name}/**", window.on_sample)
            # warm: one update done, so start-up and the first compile are outside the window
            wait(lambda: (window.latest("train/0", "train/policy_version") or 0) >= 1, startup_timeout,
                 "while warming up")
            if trajectories > 0:
                wait(lambda: window.latest_report("sim/0", "sim/segments") is not None, startup_timeout,
                     "before its first sim report")
                t0, base = window.latest_report("sim/0", "sim/segments")

                def enough() -> bool:
                    return window.latest_report("sim/0", "sim/segments")[1] - base >= trajectories

                wait(enough, max_seconds, f"before {trajectories} trajectories")
                t1 = window.latest_report("sim/0", "sim/segments")[0]
            else:
                t0 = time.time()
                wait(lambda: time.time() - t0 >= duration, duration + 60, "during the measurement")
                t1 = time.time()
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
        try:
            proc.wait(30)
        except subprocess.TimeoutExpired:
            proc.kill()
    return summarize(window.between(t0, t1), t1 - t0)


def learning_curve(config: str, overrides: list[str], name: str, timeout: float = 1800.0,
                   out_dir: str = "runs/bench") -> list[dict[str, float]]:
    """Run ``config`` to its end and return the learning curve: one point per sim stats report with
    wall seconds since launch, env steps, policy version and mean return of the last 20 episodes."""
    started = time.time()
    proc, conf = launch(config, name, overrides, out_dir)
    window = StatsWindow()
    with zenoh.open(conf) as session:
        session.declare_subscriber(f"ebrl/stats/{name}/**", window.on_sample)
        try:
            out, _ = proc.communicate(timeout=timeout)
        except subprocess.TimeoutExpired:
            proc.send_signal(signal.SIGINT)
            out, _ = proc.communicate(timeout=60)
    if proc.returncode not in (0, 130):
        raise RuntimeError(f"{name}: ebrl up failed ({proc.returncode}):\n{out}")
    with window.lock:
        reports = sorted(window.reports, key=lambda kr: kr[1]["time"])
    curve, version = [], 0.0
    for key, report in reports:
        m = report["metrics"]
        if key == "train/0":
            version = m.get("train/policy_version", version)
        elif key == "sim/0" and "sim/episode_return_mean" in m:
            curve.append({"wall_s": report["time"] - started, "env_steps": m["sim/env_steps"],
                          "policy_version": version, "return": m["sim/episode_return_mean"]})
    return curve


def _delta(reports: list[dict[str, Any]], name: str) -> float:
    values = [r["metrics"][name] for r in reports if name in r["metrics"]]
    return values[-1] - values[0] if len(values) > 1 else 0.0


def _span_s(reports: list[dict[str, Any]]) -> float:
    return reports[-1]["time"] - reports[0]["time"] if len(reports) > 1 else 0.0


def summarize(window: dict[str, list[dict[str, Any]]], duration: float) -> dict[str, Any]:
    sim, gen, train = window.get("sim/0", []), window.get("gen/0", []), window.get("train/0", [])
    dt = _span_s(sim) or duration
    out = {
        "window_s": dt,
        "trajectories": _delta(sim, "sim/segments"),
        "traj_per_s": _delta(sim, "sim/segments") / dt,
        "env_steps_per_s": _delta(sim, "sim/env_steps") / dt,
        "updates_per_s": _delta(train, "train/updates") / (_span_s(train) or duration),
    }
    last = sim[-1]["metrics"] if sim else {}
    for q in ("avg", "p50", "p99"):
        out[f"chunk_latency_{q}_ms"] = last.get(f"sim/chunk_latency_{q}_ms", float("nan"))
    # Busy fraction of each stage over the window (from spans, via the busy/<lane> metrics).
    def busy(reports: list[dict[str, Any]], prefix: str) -> float:
        fractions = [sum(v for k, v in r["metrics"].items() if k.startswith(prefix)) for r in reports[1:]]
        return statistics.fmean(fractions) if fractions else 0.0

    groups = max(1, sum(1 for k in last if k.startswith("busy/sim.g")))
    out["busy_sim"] = busy(sim, "busy/sim.g") / groups
    out["busy_gen"] = busy(gen, "busy/gen")
    out["busy_train"] = busy(train, "busy/train")
    out["idle_sim"], out["idle_gen"], out["idle_train"] = (1 - out["busy_sim"], 1 - out["busy_gen"],
                                                          1 - out["busy_train"])
    cores = len(os.sched_getaffinity(0))  # the cores runs may use, not every core of the host
    steps_busy = _delta(sim, "sim/step_busy_s") / dt  # cores' worth of time inside env.step
    out["useful_work_utilisation"] = min(1.0, (steps_busy + out["busy_gen"] + out["busy_train"]) / cores)
    return out


def raw_capacity(config: str, variants: dict[str, list[str]], seconds: float) -> dict[str, dict[str, Any]]:
    """The physical limit of each variant: raw env steps/s of the cores its simulation holds (measured once
    per distinct core set, before the runs, with nothing else running)."""
    from ebrl.envs import EnvSpec
    from ebrl.envs.worker import raw_steps_per_s
    from ebrl.sched.modes import resolve

    measured: dict[tuple[int, ...], float] = {}
    out = {}
    for variant, overrides in variants.items():
        cfg = config_mod.load(config, [*overrides, f"run.mode={base_mode(variant)}"])
        cores = tuple(resolve(cfg).sim_cores)
        if cores not in measured:
            print(f"raw simulator capacity of cores {list(cores)} ...", file=sys.stderr, flush=True)
            measured[cores] = raw_steps_per_s(EnvSpec.from_config(cfg.env), list(cores), seconds)
        out[variant] = {"sim_cores": list(cores), "raw_env_steps_per_s": measured[cores]}
    return out


def run(config: str, variants: dict[str, list[str]], duration: float, repeat: int, raw_seconds: float = 10.0,
        trajectories: int = 0) -> dict[str, Any]:
    """Measure every variant (name -> its ``--set`` overrides) ``repeat`` times, interleaved."""
    for overrides in variants.values():
        config_mod.load(config, overrides)  # fail fast on a bad config
    raw = raw_capacity(config, variants, raw_seconds) if raw_seconds > 0 else {}
    results: dict[str, list[dict[str, Any]]] = {m: [] for m in variants}
    for r in range(repeat):
        for variant, overrides in variants.items():
            print(f"[{r + 1}/{repeat}] {variant} ...", file=sys.stderr, flush=True)
            result = measure(config, variant, overrides, duration, trajectories=trajectories)
            if variant in raw:  # sim efficiency: achieved env steps/s over the raw capacity of sim's cores
                result.update(raw[variant])
                result["sim_efficiency"] = result["env_steps_per_s"] / raw[variant]["raw_env_steps_per_s"]
            results[variant].append(result)
    return results


def table(results: dict[str, list[dict[str, Any]]]) -> str:
    def med(mode: str, key: str) -> float:
        return statistics.median(x[key] for x in results[mode])

    baselines = [m for m in results if m in BASELINES]
    best = max(baselines, key=lambda m: med(m, "traj_per_s")) if baselines else None
    head = ("mode", "traj/s min-med-max", "env steps/s", "sim eff", "chunk ms avg/p50/p99", "idle sim/gen/train",
            "useful util", "vs best baseline")
    rows = [head]
    for mode, runs in results.items():
        traj = sorted(x["traj_per_s"] for x in runs)
        ratio = f"{med(mode, 'traj_per_s') / med(best, 'traj_per_s'):.2f}x" if best else "-"
        rows.append((
            mode,
            f"{traj[0]:.1f}-{statistics.median(traj):.1f}-{traj[-1]:.1f}",
            f"{med(mode, 'env_steps_per_s'):,.0f}",
            f"{med(mode, 'sim_efficiency'):.2f}" if "sim_efficiency" in runs[0] else "-",
            f"{med(mode, 'chunk_latency_avg_ms'):.0f}/{med(mode, 'chunk_latency_p50_ms'):.0f}/"
            f"{med(mode, 'chunk_latency_p99_ms'):.0f}",
            f"{med(mode, 'idle_sim'):.2f}/{med(mode, 'idle_gen'):.2f}/{med(mode, 'idle_train'):.2f}",
            f"{med(mode, 'useful_work_utilisation'):.2f}",
            ratio + (" (best)" if mode == best else ""),
        ))
    widths = [max(len(str(r[i])) for r in rows) for i in range(len(head))]
    return "\n".join("  ".join(str(c).ljust(w) for c, w in zip(r, widths)) for r in rows)


def main(config: str, modes: str, ablations: bool, duration: float, repeat: int, json_path: str,
         overrides: list[str], raw_seconds: float = 10.0, trajectories: int = 0) -> int:
    names = [m.strip() for m in modes.split(",") if m.strip()]
    unknown = [m for m in names if m not in ("ebrl", *BASELINES)]
    if unknown:
        print(f"ebrl bench: unknown mode(s) {unknown}; choose from ebrl, {', '.join(BASELINES)}", file=sys.stderr)
        return 2
    try:
        variants = {name: list(overrides) for name in names}
        if ablations:
            flips = ablation_variants(config, overrides)
            variants.update({name: [*overrides, *flip] for name, flip in flips.items()})
        results = run(config, variants, duration, repeat, raw_seconds, trajectories)
    except config_mod.ConfigError as exc:
        print(f"ebrl: config error: {exc}", file=sys.stderr)
        return 2
    print(table(results))
    if json_path:
        Path(json_path).parent.mkdir(parents=True, exist_ok=True)
        Path(json_path).write_text(json.dumps({
            "command": "ebrl " + " ".join(sys.argv[1:]), "machine": f"{len(os.sched_getaffinity(0))} usable cores",
            "config": config, "duration_s": duration, "trajectories": trajectories, "repeat": repeat,
            "overrides": overrides, "variants": variants, "results": results,
        }, indent=2) + "\n")
    return 0
