"""Zenoh between two hermetic sessions (one unix socket, no multicast): samples, the project's
PlanesServer (publish and get-latest), the acquisition service's liveliness token."""

from __future__ import annotations

import threading

import pytest
import zenoh

from lelsonar import codec
from lelsonar.errors import ConfigError, InvalidIdentifierError
from lelsonar.keys import ScannerKeys
from lelsonar.net.transport import TransportError, ZenohSettings, hermetic_settings, open_session
from lelsonar.reconstruct.stream.sources import PlanesServer

from .conftest import make_sample


def test_sample_published_by_one_session_arrives_validated_at_the_other(zenoh_socket):
    keys = ScannerKeys("lelsonar", "s1")
    with (
        open_session(hermetic_settings(zenoh_socket, listen=True)) as pub_session,
        open_session(hermetic_settings(zenoh_socket, listen=False)) as sub_session,
    ):
        sub = sub_session.declare_subscriber(ScannerKeys().sample, zenoh.handlers.FifoChannel(64))
        pub = pub_session.declare_publisher(
            keys.sample,
            congestion_control=zenoh.CongestionControl.BLOCK,
            encoding=zenoh.Encoding(codec.encoding_name(make_sample())),
        )
        # Wait for the subscription to reach the publisher instead of sleeping.
        matched = threading.Event()
        pub.declare_matching_listener(lambda status: status.matching and matched.set())
        assert matched.wait(10)
        sent = [make_sample(step=i) for i in range(5)]
        for s in sent:
            pub.put(s.SerializeToString())
        got = []
        for _ in sent:
            z = sub.recv()
            cls = codec.type_from_encoding(str(z.encoding))
            got.append(codec.decode(z.payload.to_bytes(), cls))
            assert ScannerKeys().scanner_of(str(z.key_expr)) == "s1"
        assert got == sent


def estimate(scanner_id: str, scan_id: int, last_step: int) -> codec.Reconstruction:
    return codec.Reconstruction(schema_version=1, scanner_id=scanner_id, scan_id=scan_id, last_step=last_step)


def planes_querier(session: zenoh.Session, key: str) -> zenoh.Querier:
    """A querier on ``key`` that returns once a queryable for it is reachable (matching status),
    instead of retrying a `get` until the declaration has propagated."""
    querier = session.declare_querier(key, timeout=10.0)
    matched = threading.Event()
    querier.declare_matching_listener(lambda status: status.matching and matched.set())
    assert matched.wait(10), f"no queryable for {key}"
    return querier


def replies(querier: zenoh.Querier) -> dict[str, codec.Reconstruction]:
    got = {}
    for r in querier.get():
        assert r.ok is not None, r.err
        got[str(r.ok.key_expr)] = codec.decode(r.ok.payload.to_bytes(), codec.Reconstruction)
    return got


def test_planes_server_answers_a_get_with_the_latest_estimate_per_scanner(zenoh_socket):
    """The project's PlanesServer, over the service's own `latest` table: a `get` on the planes key
    returns the newest estimate of every scanner (or of the one asked for), and follows updates."""
    latest = {"s1": estimate("s1", 3, 42), "s2": estimate("s2", 9, 7)}
    with (
        open_session(hermetic_settings(zenoh_socket, listen=True)) as server,
        open_session(hermetic_settings(zenoh_socket, listen=False)) as client,
    ):
        planes = PlanesServer(server, ScannerKeys(), latest)
        try:
            every = planes_querier(client, ScannerKeys().planes)
            assert replies(every) == {"lelsonar/s1/planes": latest["s1"], "lelsonar/s2/planes": latest["s2"]}
            only_s2 = planes_querier(client, ScannerKeys("lelsonar", "s2").planes)
            assert replies(only_s2) == {"lelsonar/s2/planes": latest["s2"]}
            latest["s1"] = estimate("s1", 4, 5)  # a newer scan's estimate replaces the old one
            assert replies(every)["lelsonar/s1/planes"] == estimate("s1", 4, 5)
        finally:
            planes.close()


def test_planes_server_publishes_each_estimate_on_its_scanner_key(zenoh_socket):
    with (
        open_session(hermetic_settings(zenoh_socket, listen=True)) as server,
        open_session(hermetic_settings(zenoh_socket, listen=False)) as client,
    ):
        sub = client.declare_subscriber(ScannerKeys().planes, zenoh.handlers.FifoChannel(16))
        # The subscription has reached the server once a publisher there matches it.
        probe = server.declare_publisher(ScannerKeys().planes)
        matched = threading.Event()
        probe.declare_matching_listener(lambda status: status.matching and matched.set())
        assert matched.wait(10)
        planes = PlanesServer(server, ScannerKeys(), {})
        try:
            sent = [estimate("s1", 1, 10), estimate("s2", 1, 3), estimate("s1", 1, 20)]
            for msg in sent:
                planes.publish(msg)
            got = []
            for _ in sent:
                z = sub.recv()
                assert codec.type_from_encoding(str(z.encoding)) is codec.Reconstruction
                got.append((str(z.key_expr), codec.decode(z.payload.to_bytes(), codec.Reconstruction)))
            assert got == [(f"lelsonar/{m.scanner_id}/planes", m) for m in sent]
            with pytest.raises(InvalidIdentifierError):
                planes.publish(estimate("../s1", 1, 1))  # never a key outside the scanner's own
        finally:
            planes.close()
            probe.undeclare()


def test_the_acquire_service_is_alive_while_it_runs_and_gone_after(tmp_path, zenoh_socket):
    """The liveliness token the acquisition service declares (not one made by the test)."""
    from lelsonar.acquire.config import AcquireConfig
    from lelsonar.acquire.service import run_acquisition

    events: list[tuple[str, zenoh.SampleKind]] = []
    gone = threading.Event()

    def on_change(sample: zenoh.Sample) -> None:
        events.append((str(sample.key_expr), sample.kind))
        if sample.kind == zenoh.SampleKind.DELETE:
            gone.set()

    with open_session(hermetic_settings(zenoh_socket, listen=True)) as watcher:
        watcher.liveliness().declare_subscriber(ScannerKeys().alive(), on_change, history=True)
        cfg = AcquireConfig(scanner_id="rig7", device="sim", steps=8, record=False, out_dir=tmp_path)
        report = run_acquisition(cfg, hermetic_settings(zenoh_socket, listen=False), threading.Event())
        assert report.ok
        assert gone.wait(10)
    assert events == [
        ("lelsonar/rig7/alive/acquire", zenoh.SampleKind.PUT),
        ("lelsonar/rig7/alive/acquire", zenoh.SampleKind.DELETE),
    ]


def test_client_without_router_names_the_fix(tmp_path):
    with pytest.raises(TransportError, match="lelsonar router"):
        with open_session(ZenohSettings(mode="client", connect=(f"unixsock-stream/{tmp_path}/none.sock",))):
            pass


def test_settings_are_validated():
    with pytest.raises(ConfigError, match="scheme"):
        ZenohSettings(connect=("127.0.0.1:7447",))
    with pytest.raises(ConfigError, match="mode"):
        ZenohSettings(mode="server")
    cfg = ZenohSettings().to_config()
    assert cfg.get_json("scouting/multicast/enabled") == "false"
