"""Does the live view keep up? A quickstart with ``--viz web`` watched by a real headless Chromium on rerun's web
viewer and by a headless native rerun viewer connected to the same server, for ``--minutes``.

    python benchmarks/viz_live.py --minutes 10
    python benchmarks/viz_live.py --minutes 5 --repo /tmp/ebrl-before --name viz_live_before   # an older checkout

Every ``--every`` seconds it reads how far behind the run each viewer is: the newest time of the data the page
holds (``tests/browser.py: newest_time``, the page's Viewer Control state) and the end of the native viewer's
timelines (``ViewerClient.get_state``), each against the wall clock, and the size of ``RUN_DIR/timeline.rrd``.
Reports each viewer's lag (median and worst after ``--settle`` seconds, and at the end) and the recording's
growth (KiB/s over the run, and the size scaled to 10 minutes). ``--repo``: run that checkout's ``ebrl`` (its
package first on PYTHONPATH) with this script's viewers and measurements, for a before/after comparison on one
machine. The run goes until stopped (``run.iterations = 0``, no target): a length to measure, not a learning
result. Needs Chromium (``apt-get install chromium``) and Vulkan for the native viewer (``mesa-vulkan-drivers``);
a viewer that cannot start is left out, saying why. Writes benchmarks/results/<name>.json.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

from browser import Chromium, find_chromium, newest_time  # noqa: E402
from ebrl.testing import free_port  # noqa: E402
from ebrl.viz import web_url  # noqa: E402

RESULTS = ROOT / "benchmarks" / "results"


def listening(port: int) -> bool:
    with socket.socket() as sock:
        sock.settimeout(0.2)
        return sock.connect_ex(("127.0.0.1", port)) == 0


def native_viewer(url: str, workdir: Path):
    """A headless native rerun viewer (this venv's) reading the run from ``url``; (client, None) or (None, why)."""
    icd = "/usr/share/vulkan/icd.d"
    if not (os.path.isdir(icd) and os.listdir(icd)):
        return None, "no Vulkan driver (apt-get install mesa-vulkan-drivers libvulkan1)"
    os.environ.setdefault("XDG_RUNTIME_DIR", str(workdir))
    os.environ.setdefault("RUST_LOG", "error")
    from rerun.experimental import ViewerClient

    exe = os.path.join(os.path.dirname(sys.executable), "rerun")
    try:
        client = ViewerClient.spawn(headless=True, port=free_port(), hide_welcome_screen=True,
                                    executable_path=exe if os.path.exists(exe) else None)
        client.get_state()
        client.open(url)
    except (ConnectionError, RuntimeError, OSError) as exc:
        return None, f"headless rerun viewer unusable here: {exc}"
    return client, None


def native_newest(client) -> float | None:
    ends = [t.end for r in client.get_state().recordings for t in r.timelines if t.end]
    return max(ends) / 1e9 if ends else None


def summary(samples: list[dict], key: str, settle: float) -> dict | None:
    lags = [s[key] for s in samples if s["t"] >= settle and s.get(key) is not None]
    if not lags:
        return None
    return {"median": round(statistics.median(lags), 2), "max": round(max(lags), 2), "last": round(lags[-1], 2),
            "samples": len(lags)}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--minutes", type=float, default=10.0)
    ap.add_argument("--every", type=float, default=10.0, help="seconds between readings")
    ap.add_argument("--settle", type=float, default=60.0,
                    help="seconds from the first reading before the lag counts (the page compiles its WebAssembly)")
    ap.add_argument("--repo", default=str(ROOT), help="the checkout whose ebrl runs (default: this one)")
    ap.add_argument("--config", default="configs/quickstart.toml")
    ap.add_argument("--name", default="viz_live_quickstart")
    args = ap.parse_args()

    exe = find_chromium()
    if exe is None:
        print("no Chromium (apt-get install chromium, or $EBRL_CHROMIUM)", file=sys.stderr)
        return 2
    repo = Path(args.repo).resolve()
    work = Path(tempfile.mkdtemp(prefix="ebrl-viz-live-"))
    port, web_port = free_port(), free_port()
    env = {**os.environ, "PYTHONPATH": str(repo)}
    cmd = [sys.executable, "-m", "ebrl.cli", "up", str(repo / args.config), "--viz", "web",
           "--set", "run.iterations=0", "--set", "run.target_return=", "--set", f"viz.port={port}",
           "--set", f"viz.web_port={web_port}", "--set", f'run.output_dir="{work / "runs"}"']
    log = open(work / "run.out", "w")
    run = subprocess.Popen(cmd, cwd=repo, env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    page = client = None
    samples: list[dict] = []
    notes: list[str] = []
    try:
        deadline = time.monotonic() + 300
        while not listening(web_port):
            if run.poll() is not None or time.monotonic() > deadline:
                print((work / "run.out").read_text()[-3000:], file=sys.stderr)
                return 1
            time.sleep(0.5)
        page = Chromium(exe, work / "chromium", 1600, 1000)
        page.send("Page.navigate", url=web_url(port, web_port))
        client, why = native_viewer(f"rerun+http://127.0.0.1:{port}/proxy", work)
        if why:
            notes.append(f"native viewer left out: {why}")
            print(notes[-1], file=sys.stderr)
        start = time.monotonic()
        while time.monotonic() - start < args.minutes * 60:
            time.sleep(args.every)
            if run.poll() is not None:
                notes.append(f"the run ended early (exit {run.returncode})")
                break
            now = time.time()
            web = newest_time(page)
            native = native_newest(client) if client is not None else None
            rrd = sorted((work / "runs").glob("*/timeline.rrd"))
            sample = {"t": round(time.monotonic() - start, 1),
                      "web_lag_s": None if web is None else round(now - web, 2),
                      "native_lag_s": None if native is None else round(now - native, 2),
                      "rrd_bytes": rrd[0].stat().st_size if rrd else 0}
            samples.append(sample)
            print(json.dumps(sample), flush=True)
        elapsed = time.monotonic() - start
        if page is not None:
            page.screenshot(work / "page.png")
    finally:
        if page is not None:
            page.close()
        if client is not None:
            client.quit()
        if run.poll() is None:
            os.killpg(run.pid, signal.SIGINT)
            try:
                run.wait(120)
            except subprocess.TimeoutExpired:
                os.killpg(run.pid, signal.SIGKILL)
                run.wait()
        log.close()
    rrd = sorted((work / "runs").glob("*/timeline.rrd"))
    size = rrd[0].stat().st_size if rrd else 0
    run_dir = rrd[0].parent if rrd else None
    wall = None
    if run_dir is not None and (run_dir / "summary.json").exists():
        wall = json.loads((run_dir / "summary.json").read_text()).get("wall_s")
    seconds = wall or elapsed
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=repo, capture_output=True,
                            text=True).stdout.strip()
    result = {
        "command": "python benchmarks/viz_live.py " + " ".join(sys.argv[1:]),
        "commit": commit, "config": args.config, "minutes": args.minutes, "settle_s": args.settle,
        "web_lag_s": summary(samples, "web_lag_s", args.settle),
        "native_lag_s": summary(samples, "native_lag_s", args.settle),
        "rrd_bytes": size, "run_s": round(seconds, 1),
        "rrd_kib_per_s": round(size / 1024 / seconds, 1) if seconds else None,
        "rrd_mb_per_10_min": round(size / seconds * 600 / 1e6, 2) if seconds else None,
        "notes": notes, "samples": samples, "work_dir": str(work),
    }
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / f"{args.name}.json").write_text(json.dumps(result, indent=1) + "\n")
    print(json.dumps({k: v for k, v in result.items() if k != "samples"}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
