"""A peer for the mesh test (tests/test_auth.py): joins the bus the way a service does (through the launcher's
endpoint, signed in with the run's secret), publishes its name on test/mesh/<name> every 50 ms, prints
"heard all" once it has heard every one of the NAMES, and leaves when its stdin closes."""

import sys
import threading
import time

import zenoh

from ebrl.bus.session import BusOptions, zenoh_config


def main(endpoint: str, secret: str, name: str, names: list[str]) -> None:
    session = zenoh.open(zenoh_config(BusOptions(connect=[endpoint], secret_file=secret, role="sim")))
    heard: set[str] = set()
    session.declare_subscriber("test/mesh/*", lambda sample: heard.add(str(sample.key_expr).rsplit("/", 1)[1]))
    stop = threading.Event()
    threading.Thread(target=lambda: (sys.stdin.read(), stop.set()), daemon=True).start()
    told = False
    while not stop.is_set():
        session.put(f"test/mesh/{name}", b"here")
        if not told and heard >= set(names):
            print("heard all", flush=True)
            told = True
        time.sleep(0.05)
    session.close()


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2], sys.argv[3], sys.argv[4].split(","))
