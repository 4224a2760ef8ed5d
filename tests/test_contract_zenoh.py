"""Zenoh pub/sub, get/queryable and liveliness between two hermetic sessions (one unix socket, no multicast)."""

from __future__ import annotations

import threading

import pytest
import zenoh

from lelsonar import codec
from lelsonar.errors import ConfigError
from lelsonar.keys import ScannerKeys
from lelsonar.transport import TransportError, ZenohSettings, hermetic_settings, open_session

from .conftest import make_sample


def test_sample_published_by_one_session_arrives_validated_at_the_other(zenoh_socket):
    keys = ScannerKeys("lelsonar", "s1")
    with open_session(hermetic_settings(zenoh_socket, listen=True)) as pub_session, \
            open_session(hermetic_settings(zenoh_socket, listen=False)) as sub_session:
        sub = sub_session.declare_subscriber(ScannerKeys().sample, zenoh.handlers.FifoChannel(64))
        pub = pub_session.declare_publisher(keys.sample, congestion_control=zenoh.CongestionControl.BLOCK,
                                            encoding=zenoh.Encoding(codec.encoding_name(make_sample())))
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


def test_get_returns_the_latest_from_a_queryable(zenoh_socket):
    keys = ScannerKeys("lelsonar", "s1")
    latest = codec.Reconstruction(schema_version=1, scanner_id="s1", scan_id=3, last_step=42)

    def answer(query: zenoh.Query) -> None:
        query.reply(keys.planes, latest.SerializeToString(), encoding=zenoh.Encoding(codec.encoding_name(latest)))

    with open_session(hermetic_settings(zenoh_socket, listen=True)) as server, \
            open_session(hermetic_settings(zenoh_socket, listen=False)) as client:
        server.declare_queryable(keys.planes, answer)
        replies = []
        for _ in range(100):  # the queryable's declaration propagates asynchronously
            replies = [r.ok for r in client.get(ScannerKeys().planes, timeout=2.0) if r.ok is not None]
            if replies:
                break
        assert len(replies) == 1
        got = codec.decode(replies[0].payload.to_bytes(), codec.Reconstruction)
        assert got == latest and str(replies[0].key_expr) == "lelsonar/s1/planes"


def test_liveliness_token_is_seen_and_its_loss_too(zenoh_socket):
    keys = ScannerKeys("lelsonar", "s1")
    alive, gone = threading.Event(), threading.Event()

    def on_change(sample: zenoh.Sample) -> None:
        (alive if sample.kind == zenoh.SampleKind.PUT else gone).set()

    with open_session(hermetic_settings(zenoh_socket, listen=True)) as watcher:
        watcher.liveliness().declare_subscriber(keys.alive(), on_change, history=True)
        with open_session(hermetic_settings(zenoh_socket, listen=False)) as service:
            token = service.liveliness().declare_token(keys.alive("acquire"))
            assert alive.wait(10)
            token.undeclare()
            assert gone.wait(10)


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
