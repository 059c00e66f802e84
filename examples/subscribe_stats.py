"""Print live throughput of a running EBRL run: subscribes to ebrl/stats/** with plain zenoh + msgpack."""
import sys, time, msgpack, zenoh

conf = zenoh.Config()
conf.insert_json5("mode", '"peer"')
conf.insert_json5("scouting/multicast/enabled", "false")
conf.insert_json5("connect/endpoints", f'["{sys.argv[1] if len(sys.argv) > 1 else "tcp/127.0.0.1:7447"}"]')
def show(sample):
    m = msgpack.unpackb(sample.payload.to_bytes())
    if "metrics" in m and m["service"] == "sim":
        print(f"{m['run']}: {m['metrics'].get('sim/env_steps_per_s', 0):,.0f} env steps/s, "
              f"{m['metrics'].get('sim/segments_per_s', 0):.1f} traj/s", flush=True)
with zenoh.open(conf) as session, session.declare_subscriber("ebrl/stats/**", show):
    time.sleep(float(sys.argv[2]) if len(sys.argv) > 2 else 1e9)
