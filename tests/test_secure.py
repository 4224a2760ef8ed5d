"""Mutual TLS and per-role access control, on loopback with keys generated in tmp_path.

Every negative is paired with a positive in the same test, on the same router, so
a test that proves "nothing is delivered" fails when the setup delivers nothing
at all.  No sleeps: deliveries are awaited on events, and a forged message sent
*before* a legitimate one (same link, or behind a get that went through the
router) would have arrived first.
"""

from __future__ import annotations

import json
import os
import queue
import socket
import stat
import subprocess
import sys
import threading
from pathlib import Path

import pytest
import zenoh

from lelsonar import SCHEMA_VERSION, codec
from lelsonar.cli.main import main
from lelsonar.errors import ScannerMismatchError, SecurityError
from lelsonar.keys import ScannerKeys
from lelsonar.net import secure
from lelsonar.net.transport import TransportError, ZenohSettings, open_session
from lelsonar.reconstruct.estimate import wire
from lelsonar.reconstruct.estimate.pipeline import DEFAULT_METHOD
from lelsonar.reconstruct.stream.ingest import Ingest, Rejected
from lelsonar.v1 import reconstruction_pb2

from .conftest import QuietObserver, make_sample, make_scan_start, type_name

KEYS1, KEYS2 = ScannerKeys("lelsonar", "scanner1"), ScannerKeys("lelsonar", "scanner2")


@pytest.fixture(scope="module")
def certs(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("secure") / "certs"
    secure.init(d, ["scanner1", "scanner2"])
    return d


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def router(certs):
    """A secure router on a loopback port; yields its endpoint."""
    endpoint = f"tls/127.0.0.1:{_free_port()}"
    settings = secure.secure_settings(
        ZenohSettings(mode="router", connect=(), listen=(endpoint,)), certs, secure.ROUTER
    )
    with open_session(settings):
        yield endpoint


def client(certs: Path, endpoint: str, role: str) -> ZenohSettings:
    return secure.secure_settings(ZenohSettings(mode="client", connect=(endpoint,)), certs, role)


def estimate(scanner: str = "scanner1", offset: float = 1.57) -> codec.Reconstruction:
    msg = codec.Reconstruction(
        schema_version=SCHEMA_VERSION, scanner_id=scanner, scan_id=1, status=reconstruction_pb2.ESTIMATE_STATUS_FINAL
    )
    plane = msg.planes.add(label="a", method="adaptive", offset=offset)
    plane.normal.y = 1.0
    return msg


class Inbox:
    """What a subscriber receives, awaited with a bound (a lost message fails the test, never hangs it)."""

    def __init__(self) -> None:
        self._queue: queue.Queue[zenoh.Sample] = queue.Queue()

    def __call__(self, sample: zenoh.Sample) -> None:
        self._queue.put(sample)

    def next(self, timeout: float = 20.0) -> zenoh.Sample:
        try:
            return self._queue.get(timeout=timeout)
        except queue.Empty:
            raise AssertionError(f"nothing arrived within {timeout} s") from None

    def empty(self) -> bool:
        return self._queue.empty()


def wait_matching(publisher) -> None:
    """Until the publisher (or querier) knows of a subscriber (queryable): the router forwarded its declaration."""
    matched = threading.Event()
    listener = publisher.declare_matching_listener(lambda status: status.matching and matched.set())
    if publisher.matching_status.matching:
        matched.set()
    assert matched.wait(30), "the subscriber's declaration never reached the publisher"
    listener.undeclare()


# --- certificates ---------------------------------------------------------------------------
def test_init_writes_private_keys_0600_signed_by_the_ca_and_never_overwrites(tmp_path):
    from cryptography import x509

    d = tmp_path / "certs"
    created = secure.init(d, ["scanner1"], hosts=["robot7.local", "10.0.0.7"])
    keys = [p for p in created if p.suffix == ".key"]
    assert sorted(p.stem for p in keys) == ["acquire-scanner1", "ca", "mapper", "planner", "reconstruct", "router"]
    for key in keys:
        assert stat.S_IMODE(key.stat().st_mode) == 0o600, key
    ca = x509.load_pem_x509_certificate((d / "ca.pem").read_bytes())
    for role in ("router", "reconstruct", "planner", "mapper", "acquire-scanner1"):
        cert = x509.load_pem_x509_certificate((d / f"{role}.pem").read_bytes())
        cert.verify_directly_issued_by(ca)
        assert secure.common_name(cert) == role
    san = (
        x509.load_pem_x509_certificate((d / "router.pem").read_bytes())
        .extensions.get_extension_for_class(x509.SubjectAlternativeName)
        .value
    )
    assert san.get_values_for_type(x509.DNSName) == ["localhost", "robot7.local"]
    assert [str(ip) for ip in san.get_values_for_type(x509.IPAddress)] == ["127.0.0.1", "10.0.0.7"]

    before = {p: p.read_bytes() for p in d.iterdir()}
    with pytest.raises(SecurityError, match="add-scanner"):
        secure.init(d, ["scanner1"])
    with pytest.raises(SecurityError, match="secure rotate"):
        secure.add_scanner(d, "scanner1")
    assert {p: p.read_bytes() for p in d.iterdir()} == before

    assert main(["secure", "add-scanner", str(d), "scanner2"]) == 0
    assert secure.SecureDir(d).scanners() == ("scanner1", "scanner2")
    for role in ("acquire-scanner1", "router"):
        old_key, old_cert = (d / f"{role}.key").read_bytes(), (d / f"{role}.pem").read_bytes()
        assert main(["secure", "rotate", str(d), role]) == 0
        assert (d / f"{role}.key").read_bytes() != old_key and (d / f"{role}.pem").read_bytes() != old_cert
        assert stat.S_IMODE((d / f"{role}.key").stat().st_mode) == 0o600
        secure.SecureDir(d).require(role)  # the same CA, the same common name
    rotated = x509.load_pem_x509_certificate((d / "router.pem").read_bytes())
    assert rotated.extensions.get_extension_for_class(x509.SubjectAlternativeName).value == san  # same hosts
    assert not list(d.glob("*.new"))


def test_a_missing_certificate_names_the_command_that_makes_it(certs):
    with pytest.raises(SecurityError, match="secure add-scanner .* scanner9"):
        client(certs, "tls/127.0.0.1:7447", secure.acquire_role("scanner9"))
    with pytest.raises(SecurityError, match="tls/"):
        client(certs, "unixsock-stream/x.sock", secure.PLANNER)


# --- the handshake -----------------------------------------------------------------------
def test_only_clients_with_a_certificate_of_this_ca_connect(certs, router, tmp_path):
    with open_session(client(certs, router, secure.PLANNER)) as legit:  # the positive: the setup can connect
        assert list(legit.info.routers_zid())

    good = client(certs, router, secure.PLANNER)
    tls_path, tls_json = next((p, v) for p, v in good.overlay if p == "transport/link/tls")
    no_cert = {k: v for k, v in json.loads(tls_json).items() if not k.startswith("connect_")}
    other = tmp_path / "other"
    secure.init(other, ["scanner1"])
    foreign = json.loads(tls_json) | {
        "connect_certificate": str(other / "planner.pem"),
        "connect_private_key": str(other / "planner.key"),
    }
    for name, tls in (("no certificate", no_cert), ("another CA's certificate", foreign)):
        settings = ZenohSettings(
            mode="client",
            connect=(router,),
            overlay=(("transport/link/protocols", '["tls"]'), (tls_path, json.dumps(tls))),
        )
        with pytest.raises(TransportError), open_session(settings):
            pytest.fail(f"a client with {name} connected")
    with (
        pytest.raises(TransportError),
        open_session(ZenohSettings(mode="client", connect=(router.replace("tls/", "tcp/"),))),
    ):
        pytest.fail("a plain TCP client connected to the TLS router")


def test_secure_config_prints_json5_that_any_zenoh_client_can_join_with(certs, router, tmp_path, capsys):
    assert main(["secure", "config", str(certs), "--role", "planner", "--connect", router]) == 0
    path = tmp_path / "planner.json5"
    path.write_text(capsys.readouterr().out)
    with zenoh.open(zenoh.Config.from_file(str(path))) as session:
        assert list(session.info.routers_zid())
    assert main(["secure", "config", str(certs), "--role", "router"]) == 0
    acl = json.loads(capsys.readouterr().out)["access_control"]
    assert acl["enabled"] and acl["default_permission"] == "deny"
    assert {s["id"] for s in acl["subjects"]} == {
        "reconstruct",
        "planner",
        "mapper",
        "acquire-scanner1",
        "acquire-scanner2",
    }


# --- access control ----------------------------------------------------------------------
def test_a_planner_cannot_forge_an_estimate(certs, router):
    from lelsonar.reconstruct.stream.sources import PlanesServer

    legit, forged = estimate(offset=1.57), estimate(offset=9.99)
    with (
        open_session(client(certs, router, secure.RECONSTRUCT)) as recon,
        open_session(client(certs, router, secure.PLANNER)) as planner,
        open_session(client(certs, router, secure.PLANNER)) as rogue,
    ):
        inbox = Inbox()
        planner.declare_subscriber(KEYS1.planes, inbox)
        server = PlanesServer(recon, ScannerKeys(), {"scanner1": legit})  # answers gets, as reconstruct does
        pub = recon.declare_publisher(KEYS1.planes)  # a declared publisher, like PlanesServer's
        wait_matching(pub)

        rogue.put(KEYS1.planes, forged.SerializeToString())
        rogue_pub = rogue.declare_publisher(KEYS1.planes)
        rogue_pub.put(forged.SerializeToString())
        # A get goes through the router after the forged puts; its answer proves they were routed (or dropped).
        replies = [r.ok.payload.to_bytes() for r in rogue.get(KEYS1.planes, timeout=5) if r.ok is not None]
        assert replies == [legit.SerializeToString()]
        pub.put(legit.SerializeToString())

        first = inbox.next()
        assert codec.decode(first.payload.to_bytes(), codec.Reconstruction).planes[0].offset == 1.57
        assert inbox.empty()
        server.close()


def test_a_scanner_cannot_publish_as_another_scanner(certs, router):
    from lelsonar.acquire.scan_loop import ScanPublisher

    with (
        open_session(client(certs, router, secure.RECONSTRUCT)) as recon,
        open_session(client(certs, router, secure.acquire_role("scanner1"))) as acquire1,
    ):
        inbox = Inbox()
        recon.declare_subscriber(ScannerKeys().sample, inbox)
        probe = acquire1.declare_publisher(KEYS1.sample)
        wait_matching(probe)

        forger = ScanPublisher(acquire1, KEYS2)  # the production publisher, on scanner2's keys
        forger.publish(make_sample(step=3, scanner_id="scanner2"))
        acquire1.put(KEYS2.sample, make_sample(step=4, scanner_id="scanner2").SerializeToString())
        own = ScanPublisher(acquire1, KEYS1)  # then its own key, on the same link: it would arrive after
        own.publish(make_sample(step=5, scanner_id="scanner1"))

        first = inbox.next()
        assert str(first.key_expr) == KEYS1.sample
        assert codec.decode(first.payload.to_bytes(), codec.Sample).step == 5
        assert inbox.empty()
        forger.close()
        own.close()

        # Liveliness too: it cannot pretend that scanner2's acquire is alive.
        tokens = Inbox()
        recon.liveliness().declare_subscriber("lelsonar/*/alive/**", tokens, history=True)
        probe = acquire1.liveliness().declare_token(KEYS1.alive("probe"))
        assert str(tokens.next().key_expr) == KEYS1.alive("probe")  # the watch is in place at the router
        fake = acquire1.liveliness().declare_token(KEYS2.alive("acquire"))
        real = acquire1.liveliness().declare_token(KEYS1.alive("acquire"))  # same link, after the fake
        assert str(tokens.next().key_expr) == KEYS1.alive("acquire")
        assert tokens.empty()
        for token in (probe, fake, real):
            token.undeclare()


def test_only_a_scanners_own_acquire_answers_for_its_log(certs, router):
    with (
        open_session(client(certs, router, secure.RECONSTRUCT)) as recon,
        open_session(client(certs, router, secure.acquire_role("scanner1"))) as acquire1,
        open_session(client(certs, router, secure.PLANNER)) as planner,
    ):
        own = acquire1.declare_queryable(
            "lelsonar/scanner1/log/**", lambda q: q.reply("lelsonar/scanner1/log/5", b"step 5")
        )
        other = acquire1.declare_queryable(
            "lelsonar/scanner2/log/**", lambda q: q.reply("lelsonar/scanner2/log/5", b"forged")
        )

        def ask(session, selector: str) -> list[bytes]:
            return [r.ok.payload.to_bytes() for r in session.get(selector, timeout=5) if r.ok is not None]

        querier = recon.declare_querier("lelsonar/scanner1/log/**")  # a querier sees the queryable, as a
        wait_matching(querier)  # publisher sees its subscribers
        assert [r.ok.payload.to_bytes() for r in querier.get() if r.ok is not None] == [b"step 5"]
        assert ask(recon, "lelsonar/scanner1/log/**") == [b"step 5"]
        assert ask(recon, "lelsonar/*/log/**") == [b"step 5"]
        assert ask(recon, "lelsonar/scanner2/log/**") == []
        assert ask(planner, "lelsonar/scanner1/log/**") == []  # planners read planes only
        own.undeclare()
        other.undeclare()


# --- identity checks, security off ----------------------------------------------------------
def test_ingest_rejects_and_counts_a_payload_that_claims_another_scanner():
    ingest = Ingest()
    start = make_scan_start(scanner_id="scanner1")
    (rejected,) = ingest.accept(type_name(start), start.SerializeToString(), key_scanner="rogue")
    assert isinstance(rejected, Rejected) and rejected.error == "ScannerMismatchError"
    assert "'scanner1'" in rejected.detail and "'rogue'" in rejected.detail
    assert ingest.rejected == {"ScannerMismatchError": 1} and not ingest.scans
    (accepted,) = ingest.accept(type_name(start), start.SerializeToString(), key_scanner="scanner1")
    assert accepted.kind == "start"


def test_live_reconstruct_rejects_a_scan_forged_under_another_key_without_security(zenoh_socket):
    from lelsonar.net.transport import hermetic_settings
    from lelsonar.reconstruct.stream.service import ReconstructionService
    from lelsonar.reconstruct.stream.sources import LiveSource

    events: list[str] = []
    rejected, started = threading.Event(), threading.Event()

    class Watch(QuietObserver):
        def scan_started(self, scan) -> None:
            started.set()

        def event(self, level: str, text: str, time_ns=None) -> None:
            events.append(text)
            if "ScannerMismatchError" in text:
                rejected.set()

    service = ReconstructionService(observer=Watch())
    stop = threading.Event()
    with (
        open_session(hermetic_settings(zenoh_socket, listen=True)) as server,
        open_session(hermetic_settings(zenoh_socket, listen=False)) as rogue,
    ):
        with LiveSource(server, ScannerKeys(), service, stop):
            rogue_keys = ScannerKeys("lelsonar", "rogue")
            pub = rogue.declare_publisher(rogue_keys.scan)
            wait_matching(pub)
            pub.put(
                make_scan_start(scanner_id="scanner1").SerializeToString(),
                encoding=zenoh.Encoding(codec.encoding_name(codec.ScanStart())),
            )
            assert rejected.wait(30), events
            legit = rogue.declare_publisher(KEYS1.scan)
            wait_matching(legit)
            legit.put(
                make_scan_start(scanner_id="scanner1").SerializeToString(),
                encoding=zenoh.Encoding(codec.encoding_name(codec.ScanStart())),
            )
            assert started.wait(30), events
    assert service.ingest.rejected["ScannerMismatchError"] == 1


def test_the_planner_refuses_an_estimate_on_another_scanners_key():
    payload = estimate("scanner1").SerializeToString()
    assert wire.decode_estimate("lelsonar/scanner1/planes", payload, "lelsonar").scanner_id == "scanner1"
    with pytest.raises(ScannerMismatchError, match="scanner2"):
        wire.decode_estimate("lelsonar/scanner2/planes", payload, "lelsonar")


def test_the_planner_process_drops_an_estimate_on_another_scanners_key_without_security(zenoh_socket):
    from lelsonar.net.transport import hermetic_settings

    endpoint = f"unixsock-stream/{zenoh_socket}"
    with open_session(hermetic_settings(zenoh_socket, listen=True)) as session:
        up = threading.Event()
        session.liveliness().declare_subscriber("lelsonar/*/alive/planner", lambda _s: up.set(), history=True)
        planner = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "lelsonar",
                "planner",
                "--json",
                "--until-final",
                "1",
                "--timeout",
                "60",
                "--connect",
                endpoint,
            ],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        try:
            assert up.wait(30), "the planner did not come up"
            pub2 = session.declare_publisher(KEYS2.planes)
            wait_matching(pub2)
            pub2.put(estimate("scanner1", offset=9.99).SerializeToString())  # scanner1's estimate, scanner2's key
            session.put(KEYS1.planes, estimate("scanner1", offset=1.57).SerializeToString())
            out, err = planner.communicate(timeout=60)
        finally:
            planner.kill()
    assert planner.returncode == 0, err
    (shown,) = [json.loads(line) for line in out.splitlines() if line.startswith("{")]
    assert shown["planes"][0]["offset"] == 1.57
    assert "ScannerMismatchError" in err and "'scanner2'" in err


# --- the whole demo, both ways --------------------------------------------------------------
def _planes_printed(out: str) -> list[str]:
    return [line for line in out.splitlines() if line.startswith("│") or " = " in line]


@pytest.mark.slow
def test_secure_demo_prints_the_same_planes_as_the_plain_demo(tmp_path):
    env = {**os.environ, "COLUMNS": "140"}
    runs = {}
    for name, extra in (("plain", []), ("secure", ["--secure", str(tmp_path / "certs")])):
        run = subprocess.run(
            [
                sys.executable,
                "-m",
                "lelsonar",
                "demo",
                "--device",
                "sim",
                "--seed",
                "3",
                "--out",
                str(tmp_path / name),
                *extra,
            ],
            capture_output=True,
            text=True,
            timeout=150,
            env=env,
        )
        assert run.returncode == 0, run.stdout + run.stderr
        runs[name] = run.stdout
    assert "mutual TLS" in runs["secure"]
    planes = _planes_printed(runs["plain"])
    assert len([line for line in planes if DEFAULT_METHOD in line]) >= 2
    assert _planes_printed(runs["secure"]) == planes


def test_reconstruct_group_members_see_each_other_and_a_planner_cannot_join_or_mark_finals(certs, router):
    from lelsonar.reconstruct.stream.group import GroupConfig, GroupMembership, finals_key, group_keys

    _, done_key = group_keys("lelsonar", "g")
    with (
        open_session(client(certs, router, secure.RECONSTRUCT)) as s_a,
        open_session(client(certs, router, secure.PLANNER)) as rogue,
    ):
        marks = Inbox()
        s_a.declare_subscriber(done_key, marks)
        with GroupMembership(s_a, "lelsonar", GroupConfig("g", "a", settle=0.0)) as a:
            # The planner tries to join the group and to mark a scan done: the router drops both.
            rogue.liveliness().declare_token("lelsonar/_group/g/member/rogue/1")
            rogue.put(done_key, b"scanner1/1")
            with (
                open_session(client(certs, router, secure.RECONSTRUCT)) as s_b,
                GroupMembership(s_b, "lelsonar", GroupConfig("g", "b", settle=0.0)) as b,
            ):
                assert sorted(b.members) == ["a", "b"]  # the join query passes the access control
                assert a.wait_members(2, 20) and b.wait_members(2, 20)
                pub = s_b.declare_publisher(done_key)
                wait_matching(pub)
                pub.put(b"scanner2/1")
                assert marks.next().payload.to_bytes() == b"scanner2/1"
                assert sorted(a.members) == ["a", "b"] and sorted(b.members) == ["a", "b"]
                assert marks.empty()
                # The fence's question reaches a's table of finals; the planner's does not.
                a.on_estimate(
                    codec.Reconstruction(
                        scanner_id="scanner3", scan_id=1, status=reconstruction_pb2.ESTIMATE_STATUS_FINAL
                    )
                )
                assert b._published_elsewhere("scanner3", 1) and not b._published_elsewhere("scanner3", 2)
                assert not list(rogue.get(finals_key("lelsonar", "g") + "?scanner=scanner3;scan=1", timeout=2.0))


def test_only_the_mapper_publishes_the_map_and_a_planner_gets_it(certs, router):
    from lelsonar.map.service import map_key
    from lelsonar.v1 import map_pb2

    key = map_key("lelsonar")
    legit, forged = map_pb2.Map(scanner_id="scanner1"), map_pb2.Map(scanner_id="forged")
    with (
        open_session(client(certs, router, secure.MAPPER)) as mapper,
        open_session(client(certs, router, secure.PLANNER)) as planner,
        open_session(client(certs, router, secure.PLANNER)) as rogue,
        open_session(client(certs, router, secure.acquire_role("scanner1"))) as acquire1,
        open_session(client(certs, router, secure.RECONSTRUCT)) as recon,
    ):
        estimates = Inbox()  # the mapper reads the reconstructor's estimates
        mapper.declare_subscriber(KEYS1.planes, estimates)
        planes = recon.declare_publisher(KEYS1.planes)
        wait_matching(planes)
        planes.put(estimate().SerializeToString())
        assert codec.decode(estimates.next().payload.to_bytes(), codec.Reconstruction).scanner_id == "scanner1"

        inbox = Inbox()
        planner.declare_subscriber(key, inbox)
        queryable = mapper.declare_queryable(key, lambda query: query.reply(key, legit.SerializeToString()))
        pub = mapper.declare_publisher(key)
        wait_matching(pub)

        rogue.put(key, forged.SerializeToString())
        acquire1.put(key, forged.SerializeToString())
        # A get goes through the router after the forged puts; its answer proves they were routed (or dropped),
        # and that a planner may ask the mapper for the latest map.
        replies = [r.ok.payload.to_bytes() for r in rogue.get(key, timeout=5) if r.ok is not None]
        assert replies == [legit.SerializeToString()]
        pub.put(legit.SerializeToString())

        assert map_pb2.Map.FromString(inbox.next().payload.to_bytes()).scanner_id == "scanner1"
        assert inbox.empty()
        queryable.undeclare()
