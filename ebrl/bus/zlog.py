"""Zenoh's own account of the links it refuses, said as EBRL lines.

Zenoh (Rust) tells of a refused TLS handshake or a refused sign-in only in its own log, which is off unless turned
on and which it writes to the process's standard output (descriptor 1). A launcher that other hosts connect to
turns on just the lines that tell of a link accepted or refused (:data:`FILTER`) and reads them from a pipe put in
place of descriptor 1 (:class:`ZenohLog`): each refusal becomes one plain line (:func:`refusal`), handed to
``on_refusal``; any other warning or error Zenoh writes passes through, without its colours. Python's own output
goes on to the terminal unchanged: ``sys.stdout`` moves to a copy of the original descriptor first.

What a refusal line can say is what Zenoh logs: a refused sign-in names the address it came from (the TCP or TLS
accept just before it on the same thread); a refused TLS handshake does not (rustls reports the alert alone).
"""

from __future__ import annotations

import io
import os
import re
import sys
import threading
import time
from typing import Callable

# the accepts of zenoh's TCP and TLS links (where a host came from) and the establishment's refusals
FILTER = "zenoh_link_tcp=debug,zenoh_link_tls=debug,zenoh_transport::unicast::establishment::accept=debug"
ANSI = re.compile(r"\x1b\[[0-9;]*m")
LINE = re.compile(r"^\S+\s+(?P<level>TRACE|DEBUG|INFO|WARN|ERROR)\s+(?:\S+\s+)?ThreadId\((?P<thread>\d+)\)\s+"
                  r"(?P<target>[\w:]+):\s*(?P<text>.*)$")
ACCEPTED = re.compile(r"Accepted (?:TCP|TLS) connection on \S+: (?P<peer>[^\s,]+?)\.?(?:\s|$)")
ALERT = re.compile(r"received fatal alert: (?P<alert>\w+)")
SAY_AGAIN_S = 60.0  # the same refusal is said at most once a minute (a refused host retries every few seconds)


def host_of(peer: str) -> str:
    """``127.0.0.1`` of ``127.0.0.1:38566``, ``::1`` of ``[::1]:38566``."""
    return peer.rpartition(":")[0].strip("[]") or peer


def refusal(target: str, text: str, peer: str | None) -> str | None:
    """The line for a Zenoh log line that tells of a refused link (None: it does not). ``peer``: the address of
    the link this thread accepted last, where the refusal came after an accept."""
    if target.startswith("zenoh_link_tls") and (alert := ALERT.search(text)):
        if alert["alert"] == "UnknownCA":
            return ("a host was refused at the TLS handshake: the CA it checks this host's certificate against (its "
                    "root_ca_certificate) did not sign it (UnknownCA)")
        return f"a host broke off the TLS handshake ({alert['alert']})"
    if "UsrPwd" in text and "Invalid" in text:
        where = f" at {host_of(peer)}" if peer else ""
        return (f"a host{where} was refused at sign-in: its bus.secret_file is not this run's (another run's, or one "
                "it wrote itself)")
    return None


_turned_on = False  # Zenoh's log: once per process


def _say(line: str) -> None:
    print(f"ebrl: {line}", file=sys.stderr, flush=True)


class ZenohLog:
    """Read Zenoh's log from a pipe in place of descriptor 1 (see the module docstring). ``on_refusal(line)`` runs
    on the reader thread, once per refusal and at most every :data:`SAY_AGAIN_S` per distinct line (until it is
    set: printed to stderr); ``refused`` counts every refusal. ``passthrough``: where other Zenoh warnings and
    errors go (stderr)."""

    def __init__(self, on_refusal: Callable[[str], None] = _say, passthrough=None):
        self.on_refusal = on_refusal
        self.passthrough = passthrough
        self.refused = 0
        self._peers: dict[str, str] = {}  # thread -> the address it accepted a link from last
        self._said: dict[str, float] = {}
        self._saved: tuple[int, object] | None = None  # descriptor 1's copy, and sys.stdout before
        self.everything = False  # RUST_LOG set: the user asked for Zenoh's log, every line of it passes
        self._thread: threading.Thread | None = None

    def start(self, level_filter: str = FILTER) -> bool:
        """Put the pipe in place of descriptor 1 and turn Zenoh's log on (once per process: it cannot be turned
        off again); ``sys.stdout`` is then a new object: take it after this. False, changing nothing, where
        ``sys.stdout`` is not descriptor 1 (a test capturing output) or the log is on already."""
        global _turned_on
        try:
            if _turned_on or sys.stdout.fileno() != 1:
                return False
        except (AttributeError, ValueError, io.UnsupportedOperation):
            return False
        import zenoh

        _turned_on = True
        sys.stdout.flush()
        original = os.dup(1)
        read, write = os.pipe()
        os.dup2(write, 1)
        os.close(write)
        old = sys.stdout
        sys.stdout = open(original, "w", buffering=1, encoding="utf-8", closefd=False)
        self._saved = (original, old)
        if self.passthrough is None:
            self.passthrough = sys.stderr
        self._thread = threading.Thread(target=self._read, args=(read,), name="zenoh-log", daemon=True)
        self._thread.start()
        self.everything = bool(os.environ.get("RUST_LOG"))
        zenoh.init_log_from_env_or(level_filter)  # RUST_LOG, where set, wins: its lines pass through as well
        return True

    def _read(self, fd: int) -> None:
        with os.fdopen(fd, "rb") as pipe:
            for raw in pipe:
                try:
                    self.feed(raw.decode("utf-8", "replace"))
                except Exception:  # a line it cannot place never stops the reading (a full pipe would block Zenoh)
                    pass

    def feed(self, line: str, now: float | None = None) -> None:
        """One line Zenoh wrote: remember an accept's address, say a refusal, pass a warning or error on."""
        plain = ANSI.sub("", line).rstrip("\n")
        parsed = LINE.match(plain)
        if parsed is None:
            if plain.strip():
                print(plain, file=sys.stdout, flush=True)  # not Zenoh's (a library writing to descriptor 1)
            return
        thread, target, text = parsed["thread"], parsed["target"], parsed["text"]
        if accepted := ACCEPTED.search(text):
            self._peers[thread] = accepted["peer"]
        said = refusal(target, text, self._peers.get(thread))
        if said is None:
            if parsed["level"] in ("WARN", "ERROR") or self.everything:
                print(f"zenoh: {parsed['level'].lower()}: {target}: {text}", file=self.passthrough, flush=True)
            return
        self.refused += 1
        now = time.monotonic() if now is None else now
        if now - self._said.get(said, -SAY_AGAIN_S) >= SAY_AGAIN_S:
            self._said[said] = now
            self.on_refusal(said)

    def stop(self) -> None:
        """Give descriptor 1 and ``sys.stdout`` back (Zenoh's sessions closed by now); the reader ends at EOF."""
        if self._saved is None:
            return
        original, old = self._saved
        self._saved = None
        sys.stdout.flush()
        sys.stdout.close()  # the copy's descriptor stays open (closefd=False) until closed below
        sys.stdout = old  # type: ignore[assignment]
        os.dup2(original, 1)  # the pipe's last writer gone: the reader sees its end
        os.close(original)
        if self._thread is not None:
            self._thread.join(timeout=2.0)
