"""A hostile process on the same machine as a run: joins the run's bus at its endpoint and, until the run's
launcher is gone, tries to read its data and to stop, poison and end it. Prints one JSON line of what it got.

    python tests/hostile_peer.py ENDPOINT RUN RUN_DIR

It has no credentials: it tries to read RUN_DIR/bus.secret, as an outsider would, and joins without. It stops
when its standard input closes.
"""

from __future__ import annotations

import json
import os
import sys
import threading
import time

import zenoh

from ebrl.bus import BusOptions, auth, keys, zenoh_config
from ebrl.messages import StatsReport, Stop, Weights, encode_message


def attacks(run: str) -> list[tuple[str, bytes]]:
    """What it publishes, each a well-formed message: if one arrived, the run would show it."""
    now = time.time()
    out = [(keys.ctl(run, role, 0, "stop"), encode_message(Stop(reason="hostile stop")))
           for role in ("train", "gen", "sim", "launcher")]
    out.append((keys.ctl(run, "launcher", "all", "stop"), encode_message(Stop(reason="hostile stop"))))
    # a weights version far ahead: generation would ignore every real update after it
    out.append((keys.weights(run), encode_message(Weights(version=10**9, params={}, created_at=now))))
    # a made-up training report of a late version: the launcher would end the run as finished
    out.append((keys.stats(run, "train", 9), encode_message(StatsReport(
        run=run, service="train", instance=9, time=now, seq=0,
        metrics={"train/policy_version": 10.0**6, "train/iteration": 10.0**6}))))
    out.append((keys.traj(run, 0), os.urandom(64)))
    return out


def main() -> int:
    endpoint, run, run_dir = sys.argv[1:4]
    secret = os.path.join(run_dir, auth.FILENAME)
    try:
        with open(secret):
            readable = True
    except OSError:
        readable = False
    options = BusOptions(mode="peer", connect=[endpoint], listen=["tcp/127.0.0.1:0"])
    received: dict[str, int] = {}

    def on_sample(sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        received[key] = received.get(key, 0) + 1

    session = zenoh.open(zenoh_config(options))
    session.declare_subscriber("ebrl/**", on_sample)
    live = []
    session.liveliness().declare_subscriber("ebrl/live/**", lambda s: live.append(str(s.key_expr)), history=True)
    token = session.liveliness().declare_token(keys.live(run, "train", 7))  # would look like a second trainer
    done = threading.Event()
    threading.Thread(target=lambda: (sys.stdin.read(), done.set()), daemon=True).start()  # EOF: the run ended
    sent = 0
    peers = 0
    big = os.urandom(8 << 20)
    while not done.is_set():
        peers = max(peers, len(list(session.info.peers_zid())))
        for key, payload in attacks(run):
            session.put(key, payload)
            sent += 1
        session.put(keys.traj(run, 1), big)  # 8 MB of garbage on a data key
        done.wait(0.05)
    del token
    own = sorted({key for key, _ in attacks(run)} | {keys.traj(run, 1)})
    print(json.dumps({"secret_readable": readable, "peers": peers, "received": received, "own": own, "sent": sent,
                      "liveliness": sorted(set(live)), "uid": os.getuid()}), flush=True)
    os._exit(0)  # zenoh's threads would hold interpreter exit


if __name__ == "__main__":
    sys.exit(main())
