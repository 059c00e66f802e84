"""A host that cannot join a run says why (ebrl.bus.joincheck), and the host it tried says it refused one
(ebrl.bus.zlog): against a real Zenoh TLS router with certificates made by openssl. The whole runs, hosts in
network namespaces: tests/test_hosts.py (slow)."""

from __future__ import annotations

import asyncio
import io
import json
import os
import socket
import subprocess
import sys
import textwrap
import time

import pytest
import zenoh

import helpers
import tlscerts
from ebrl import prepare
from ebrl.bus import auth
from ebrl.bus.endpoints import free_port
from ebrl.bus.joincheck import Cause, await_link, certificate_problem, diagnose, split_endpoint
from ebrl.bus.zlog import ZenohLog, refusal

# lines as Zenoh 1.10 writes them (its colours included)
ACCEPT = ("\x1b[2m2026-11-29T02:34:58.260896Z\x1b[0m \x1b[34mDEBUG\x1b[0m acc-0 ThreadId(05) \x1b[2mzenoh_link_tls::"
          "unicast\x1b[0m\x1b[2m:\x1b[0m Accepted TLS connection on 127.0.0.1:17447: 192.0.2.7:38566. Common Name: None.")
BAD_PASSWORD = ("\x1b[2m2026-11-29T02:34:58.261670Z\x1b[0m \x1b[34mDEBUG\x1b[0m acc-0 ThreadId(05) \x1b[2mzenoh_transport"
                "::unicast::establishment::accept\x1b[0m\x1b[2m:\x1b[0m UsrPwd extension - Recv OpenSyn. Invalid "
                "password. at /root/.cargo/git/checkouts/zenoh/io/zenoh-transport/src/unicast/establishment/ext/auth/"
                "usrpwd.rs:424.")
UNKNOWN_CA = ("\x1b[2m2026-11-29T02:34:30.078291Z\x1b[0m \x1b[33m WARN\x1b[0m acc-0 ThreadId(05) \x1b[2mzenoh_link_tls::"
              "unicast\x1b[0m\x1b[2m:\x1b[0m received fatal alert: UnknownCA. Hint: increase the system open file limit.")
TCP_ACCEPT = ("2026-11-29T02:36:40.926722Z DEBUG acc-0 ThreadId(05) zenoh_link_tcp::unicast: Accepted TCP connection "
              "on 127.0.0.1:17449: 127.0.0.1:35004")
OTHER_WARN = "2026-11-29T02:36:40.926722Z  WARN net-0 ThreadId(03) zenoh::net::runtime: something else happened"


def test_zenoh_refusals_become_one_line_each_naming_the_host_where_zenoh_does():
    said, other = [], io.StringIO()
    log = ZenohLog(said.append, passthrough=other)
    for line in (ACCEPT, BAD_PASSWORD, BAD_PASSWORD, UNKNOWN_CA, TCP_ACCEPT, OTHER_WARN):
        log.feed(line + "\n", now=100.0)
    assert log.refused == 3
    assert said == ["a host at 192.0.2.7 was refused at sign-in: its bus.secret_file is not this run's (another run's, "
                    "or one it wrote itself)",
                    "a host was refused at the TLS handshake: the CA it checks this host's certificate against (its "
                    "root_ca_certificate) did not sign it (UnknownCA)"]  # the second sign-in: counted, not said again
    assert other.getvalue() == "zenoh: warn: zenoh::net::runtime: something else happened\n"
    log.feed(BAD_PASSWORD, now=161.0)  # a minute on: said again
    assert len(said) == 3 and log.refused == 4
    assert refusal("zenoh_link_tls::unicast", "received fatal alert: BadCertificate", None) == (
        "a host broke off the TLS handshake (BadCertificate)")
    assert refusal("zenoh_link_tcp::unicast", "Accepted TCP connection on a: b", None) is None


def test_the_log_is_read_from_descriptor_1_while_python_prints_as_before(tmp_path):
    """In a process of its own (Zenoh's log is turned on once per process): a router with a password file, a
    client with a wrong password; the refusal comes back as a line, Python's prints reach the terminal."""
    (tmp_path / "dict.txt").write_text("a:right\n")
    port = free_port()
    script = textwrap.dedent(f"""
        import json, sys, time, zenoh
        from ebrl.bus.zlog import ZenohLog
        log = ZenohLog(lambda line: print("REFUSED", line, flush=True))
        assert log.start()
        print("python prints", flush=True)
        server = zenoh.Config()
        server.insert_json5("mode", '"router"')
        server.insert_json5("listen/endpoints", '["tcp/127.0.0.1:{port}"]')
        server.insert_json5("transport/auth/usrpwd", json.dumps({{"dictionary_file": "dict.txt"}}))
        router = zenoh.open(server)
        client = zenoh.Config()
        client.insert_json5("mode", '"client"')
        client.insert_json5("connect/endpoints", '["tcp/127.0.0.1:{port}"]')
        client.insert_json5("transport/auth/usrpwd", json.dumps({{"user": "a", "password": "wrong"}}))
        try:
            zenoh.open(client)
        except zenoh.ZError:
            pass
        deadline = time.monotonic() + 30
        while not log.refused and time.monotonic() < deadline:
            time.sleep(0.05)
        router.close()
        log.stop()
        print("restored", flush=True)
    """)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(helpers.ROOT), os.environ.get("PYTHONPATH")]))}
    env.pop("RUST_LOG", None)
    done = subprocess.run([sys.executable, "-c", script], cwd=tmp_path, capture_output=True, text=True, timeout=120,
                          env=env)
    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    assert lines[0] == "python prints" and lines[-1] == "restored", done.stdout
    assert "REFUSED a host at 127.0.0.1 was refused at sign-in: its bus.secret_file is not this run's" in done.stdout
    assert "\x1b[" not in done.stdout  # none of Zenoh's own lines came through


@pytest.fixture(scope="module")
def tls(tmp_path_factory):
    """A Zenoh router listening on TLS (certificate from CA ``right``), and a CA ``wrong`` that did not sign it."""
    if why := tlscerts.unavailable():
        pytest.skip(why)
    where = tmp_path_factory.mktemp("tls")
    right, wrong = tlscerts.make_ca(where, "right"), tlscerts.make_ca(where, "wrong")
    cert = tlscerts.make_cert(where, right, "learner", ["127.0.0.1"])
    endpoint = f"tls/127.0.0.1:{free_port()}"
    conf = zenoh.Config.from_file(str(tlscerts.zenoh_tls(where / "learner.json5", right, cert)))
    conf.insert_json5("mode", '"router"')
    conf.insert_json5("listen/endpoints", json.dumps([endpoint]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    session = zenoh.open(conf)
    yield {"endpoint": endpoint, "where": where, "right": right, "wrong": wrong}
    session.close()


def test_a_learner_that_comes_up_late_is_waited_for_and_joined_not_called_a_refused_sign_in(tls):
    """A real joining router (Zenoh's own retries) whose learner starts listening 7 s later: the probes say
    nothing listens yet, then that it answers; the link Zenoh's next try makes ends the wait (a probe alone
    would have called the answer a refused sign-in)."""
    import threading

    endpoint = f"tls/127.0.0.1:{free_port()}"
    joining = zenoh.Config.from_file(str(tlscerts.zenoh_tls(tls["where"] / "right.json5", tls["right"])))
    joining.insert_json5("mode", '"router"')
    joining.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{free_port()}"]))
    joining.insert_json5("connect/endpoints", json.dumps([endpoint]))
    joining.insert_json5("scouting/multicast/enabled", "false")
    learner = zenoh.Config.from_file(str(tls["where"] / "learner.json5"))
    learner.insert_json5("mode", '"router"')
    learner.insert_json5("listen/endpoints", json.dumps([endpoint]))
    learner.insert_json5("scouting/multicast/enabled", "false")
    sessions = []
    late = threading.Timer(7.0, lambda: sessions.append(zenoh.open(learner)))
    said: list[str] = []
    with zenoh.open(joining) as session:
        late.start()
        try:
            problem = asyncio.run(await_link(lambda: bool(list(session.info.routers_zid())), [endpoint],
                                             lambda e: diagnose(e, str(tls["where"] / "right.json5"), "/s", "r"),
                                             said.append, 60.0))
        finally:
            late.join()
            for opened in sessions:
                opened.close()
    assert problem is None, problem
    assert said and said[0].startswith(f"nothing listens at {endpoint} yet"), said


def test_a_certificate_from_another_ca_is_named_with_the_ca_it_was_checked_against(tls):
    config = tlscerts.zenoh_tls(tls["where"] / "wrong.json5", tls["wrong"])
    cause = diagnose(tls["endpoint"], str(config))
    assert cause.final and "its certificate does not verify against the CA in root_ca_certificate" in cause.line
    assert str(tls["wrong"]) in cause.line and tls["endpoint"] in cause.line


def test_no_ca_in_the_config_file_is_said(tls):
    cause = diagnose(tls["endpoint"], str(tlscerts.zenoh_tls(tls["where"] / "none.json5", None)))
    assert cause.final and "the system's CAs (bus.config_file names no root_ca_certificate)" in cause.line


def test_a_handshake_that_goes_through_leaves_the_sign_in(tls):
    config = tlscerts.zenoh_tls(tls["where"] / "right.json5", tls["right"])
    cause = diagnose(tls["endpoint"], str(config), "/path/my.secret", "myrun")
    assert cause.final and "refused this host's sign-in: bus.secret_file = '/path/my.secret'" in cause.line


def test_a_plain_endpoint_where_tls_listens_fails_its_handshake(tls):
    """A tls/ client at a plain port: the handshake breaks off (Zenoh's own TLS port, asked in plain TCP, says
    nothing that EBRL could read, so the other direction is the one checked)."""
    with socket.socket() as server:
        server.bind(("127.0.0.1", 0))
        server.listen()
        endpoint = f"tls/127.0.0.1:{server.getsockname()[1]}"
        cause = diagnose(endpoint, str(tlscerts.zenoh_tls(tls["where"] / "right.json5", tls["right"])), timeout=0.5)
    assert cause.final and cause.line.startswith(f"the TLS handshake with {endpoint} failed")


def test_nothing_listening_yet_is_waited_for_and_other_causes_are_not():
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    cause = diagnose(endpoint)
    assert not cause.final and cause.line.startswith(f"nothing listens at {endpoint} yet")
    assert split_endpoint("tls/[::1]:7447#iface=lo") == ("tls", "::1", 7447)
    assert split_endpoint("serial//dev/ttyUSB0") is None
    assert "not an address EBRL can look into" in diagnose("serial//dev/ttyUSB0").line


def test_await_link_stops_on_a_final_cause_waits_on_the_rest_and_ends_with_the_link():
    said: list[str] = []

    def run(linked, causes, patience=5.0, check_after=0.05):
        return asyncio.run(await_link(linked, ["a", "b"], lambda e: causes[e], said.append, patience, check_after))

    final = {"a": Cause("a", "no route to a"), "b": Cause("b", "tls of b")}
    assert run(lambda: False, final) == "no route to a; tls of b" and not said
    waiting = {"a": Cause("a", "no route to a"), "b": Cause("b", "nothing listens at b yet", final=False)}
    assert run(lambda: False, waiting, patience=0.3) == "no route to a; nothing listens at b yet"
    assert said == ["nothing listens at b yet; waiting for it (at most run.startup_timeout = 0.3 s)"]
    calls = iter([False] * 3 + [True] * 100)
    assert run(lambda: next(calls), final, check_after=30.0) is None  # the link came before the check
    # an endpoint that answers (a learner that has just come up) is a refused sign-in only after the grace
    answers = {"a": Cause("a", "a refused this host's sign-in", reached=True),
               "b": Cause("b", "b refused this host's sign-in", reached=True)}
    started = time.monotonic()
    assert asyncio.run(await_link(lambda: False, ["a", "b"], lambda e: answers[e], said.append, 30.0, 0.05,
                                  grace_s=1.0)) == "a refused this host's sign-in; b refused this host's sign-in"
    assert time.monotonic() - started >= 1.0
    linked_soon = iter([False] * 8 + [True] * 100)  # Zenoh's next try links it within the grace
    assert asyncio.run(await_link(lambda: next(linked_soon), ["a"], lambda e: answers[e], said.append, 30.0, 0.05,
                                  grace_s=5.0)) is None


def test_a_missing_certificate_is_a_config_error_naming_it(tmp_path):
    config = tlscerts.zenoh_tls(tmp_path / "z.json5", tmp_path / "ca.pem")
    assert certificate_problem(str(config)) == (
        f"bus.config_file = {str(config)!r}: transport.link.tls.root_ca_certificate = {str(tmp_path / 'ca.pem')!r}: "
        "no such file")
    (tmp_path / "ca.pem").write_text("x")
    assert certificate_problem(str(config)) is None and certificate_problem("") is None
    with pytest.raises(prepare.NotStarted, match=r"transport.link.tls.root_ca_certificate = .*: no such file"):
        (tmp_path / "ca.pem").unlink()
        prepare.prepare("configs/quickstart.toml", [f'bus.config_file="{config}"', 'viz.rerun="off"'])


def test_a_joining_host_never_writes_the_runs_secret_and_the_primary_says_it_wrote_one(tmp_path, capsys):
    secret = tmp_path / "run.secret"
    common = [f'bus.secret_file="{secret}"', 'viz.rerun="off"', f'run.output_dir="{tmp_path / "runs"}"']
    with pytest.raises(prepare.NotStarted, match="no such file; a host that joins a run signs in with the primary"):
        prepare.prepare("configs/quickstart.toml", common, only="sim", instance=1)
    assert not secret.exists()
    run = prepare.prepare("configs/quickstart.toml", common, only="gen,train")
    assert f"wrote a new secret for the run at {secret}" in capsys.readouterr().out
    assert auth.load(secret, "launcher") and run.plan.primary


def test_an_address_that_does_not_answer_is_no_route():
    """192.0.2.0/24 is TEST-NET-1: nothing answers there (or no route leads there at all)."""
    cause = diagnose("tls/192.0.2.99:7447", timeout=0.5)
    assert cause.final
    assert cause.line.startswith(("no answer from tls/192.0.2.99:7447 within 0.5 s (no route to it",
                                  "no route to tls/192.0.2.99:7447 from this host")), cause.line
