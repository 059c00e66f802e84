"""An insider holding a simulator's credential floods that simulator's stats key with frozen reports (issue 52).

    python tests/sim_report_flood.py ROLE[/N] ENDPOINT RUN RUN_DIR RATE

Signed in as ``tests/hostile_peer.py --insider`` signs in (ROLE/N: that instance's own line, as the run's
launcher hands it to the process; ROLE: the role's line of the run's secret), it sends RATE reports a second on
``ebrl/stats/<RUN>/<ROLE>/<N>`` until its standard input closes: what that identity may send, each report the
same -- env steps frozen at ``FROZEN_STEPS``, a return of 1e9, a success rate of 1 -- and marked with ``SEQ``.
The run must neither kill the real, stepping simulator nor take these numbers as its own. It prints one JSON
line: reports sent, seconds, the rate reached, and the routers it had a session with (1: it signed in).
"""

from __future__ import annotations

import json
import os
import sys
import threading
import time

import zenoh

from ebrl import keys
from ebrl.bus import auth
from ebrl.bus.session import BusOptions, zenoh_config
from ebrl.messages import StatsReport, encode_message

SEQ = 555_000_111  # the seq of every flooded report
FROZEN_STEPS = 10.0
METRICS = {"sim/env_steps": FROZEN_STEPS, "sim/episode_return_mean": 1e9, "sim/success_rate": 1.0,
           "sim/episodes": 1e6, "sim/segments": 3.0, "sim/env_steps_per_s": 1e7}


def session(who: str, endpoint: str, run_dir: str) -> zenoh.Session:
    """A Zenoh session signed in as ``who`` (``ROLE/N`` or ``ROLE``), as hostile_peer.py's insider signs in."""
    role, _, instance = who.partition("/")
    secret = os.path.join(run_dir, auth.FILENAME)
    identity = auth.instance_line(secret, role, int(instance)) if instance else ""
    return zenoh.open(zenoh_config(BusOptions(mode="client", connect=[endpoint], listen=[], secret_file=secret,
                                              role=role, identity=identity)))


def main(who: str, endpoint: str, run: str, run_dir: str, rate: str) -> int:
    role, _, instance = who.partition("/")
    n = int(instance or 0)
    bus = session(who, endpoint, run_dir)
    key = keys.stats(run, role, n)
    done = threading.Event()
    threading.Thread(target=lambda: (sys.stdin.read(), done.set()), daemon=True).start()
    every = 1.0 / float(rate)
    sent, routers, started = 0, 0, time.monotonic()
    while not done.is_set():
        if sent % 100 == 0:
            routers = max(routers, len(list(bus.info.routers_zid())))
        bus.put(key, encode_message(StatsReport(run=run, service=role, instance=n, time=time.time(), seq=SEQ,
                                                metrics=METRICS)))
        sent += 1
        done.wait(max(0.0, started + sent * every - time.monotonic()))  # paced: RATE a second on average
    seconds = time.monotonic() - started
    print(json.dumps({"sent": sent, "seconds": round(seconds, 1), "rate": round(sent / max(seconds, 1e-9), 1),
                      "routers": routers}), flush=True)
    os._exit(0)  # zenoh's threads would hold interpreter exit


if __name__ == "__main__":
    sys.exit(main(*sys.argv[1:6]))
