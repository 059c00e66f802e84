"""Print live throughput of a running EBRL run: python subscribe_stats.py RUN_DIR [SECONDS]."""
import sys, time, msgpack, zenoh
from ebrl.stats import observer_config  # signs in with RUN_DIR/bus.secret; connects to the run's launcher

def show(sample):
    m = msgpack.unpackb(sample.payload.to_bytes())
    if "metrics" in m and m["service"] == "sim":
        print(f"{m['run']}: {m['metrics'].get('sim/env_steps_per_s', 0):,.0f} env steps/s, "
              f"{m['metrics'].get('sim/segments_per_s', 0):.1f} traj/s", flush=True)
with zenoh.open(observer_config(sys.argv[1])) as session, session.declare_subscriber("ebrl/stats/**", show):
    time.sleep(float(sys.argv[2]) if len(sys.argv) > 2 else 1e9)
