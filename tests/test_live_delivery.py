"""Gap-free live delivery over Zenoh (hermetic unix socket): recovery from the acquirer's log,
INCOMPLETE when a gap cannot be filled, late start, ordering under saturation, a worker that
survives a bug."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from lelsonar import codec
from lelsonar.reconstruct.estimate import wire
from lelsonar.reconstruct.estimate.record import ScanInput
from lelsonar.reconstruct.stream.config import ReconstructConfig
from lelsonar.reconstruct.stream.recovery import RecoveryConfig
from lelsonar.reconstruct.stream.scan_input import scan_input
from lelsonar.reconstruct.stream.service import ReconstructionService

from .conftest import QuietObserver, simulated_messages, type_name
from .live_rig import Rig, renamed

STEPS = 120


@pytest.fixture(scope="module")
def scan():
    return simulated_messages("paper-test1", seed=5, scanner_id="rig", scan_id=42, steps=STEPS)


def replayed_final(messages, observer=None) -> codec.Reconstruction:
    """The independent truth: the same messages, all of them, straight through the replay path."""
    service = ReconstructionService(ReconstructConfig(provisional=False), observer=observer)
    for m in messages:
        service.handle(type_name(m), m.SerializeToString())
    (final,) = service.finish() or list(service.finals.values())
    return final


class FinalInput(QuietObserver):
    """An observer keeping the :class:`ScanInput` each final estimate was made from."""

    def __init__(self) -> None:
        self.inputs: list[ScanInput] = []

    def estimate(self, scan, message, results, partial) -> None:
        if results is not None:  # a terminal estimate, before the service forgets its scan
            self.inputs.append(scan_input(scan))


def assert_same_input(live: ScanInput, replayed: ScanInput) -> None:
    """Field by field, bit for bit: what the reconstruction of record reads."""
    for name in ("steps", "gamma", "distance", "sensor_energy", "echo_amplitude", "own_distance", "own_amplitude"):
        a, b = getattr(live, name), getattr(replayed, name)
        assert (a is None) == (b is None), name
        if a is not None:
            assert a.dtype == b.dtype and np.array_equal(a, b, equal_nan=True), name
    assert live.writer_problems == replayed.writer_problems and live.n_schedule == replayed.n_schedule


def estimate_only(msg: codec.Reconstruction) -> codec.Reconstruction:
    m = codec.Reconstruction()
    m.CopyFrom(msg)
    for f in ("stamp_ns", "timings", "accounting"):
        m.ClearField(f)
    return m


def accounting(msg) -> tuple:
    a = msg.accounting
    return a.published, a.received_live, a.recovered, a.duplicates, dict(a.rejected), a.missing


def test_dropped_samples_are_recovered_from_the_acquirers_log(scan, zenoh_socket):
    rng = np.random.default_rng(11)
    dropped = set(int(s) for s in rng.choice(STEPS, size=17, replace=False)) | {0, STEPS - 1}
    live, replayed = FinalInput(), FinalInput()
    with Rig(zenoh_socket) as rig:
        service = rig.start_reconstructor(ReconstructionService(rig.config, publish=rig.collect, observer=live))
        rig.acquirer("rig").send(scan, unpublished=dropped)
        assert rig.done.wait(30), f"no terminal estimate; stats {service.stats_dict()}"
    (final,) = rig.terminal
    assert wire.status_name(final) == "final" and list(final.missing_steps) == []
    assert accounting(final) == (STEPS, STEPS - len(dropped), len(dropped), 0, {}, 0)
    again = replayed_final(scan, replayed)
    assert_same_input(live.inputs[0], replayed.inputs[0])
    # Every surface of the sweep too (the scene's two walls and their corner), bit for bit.
    assert len(final.surfaces) == 2 and len(final.corners) == 1
    assert estimate_only(final) == estimate_only(again)
    assert rig.live.errors == 0 and rig.live.recovery_stats.get("delivered") == len(dropped)


def test_unrecoverable_gap_is_published_incomplete_with_its_missing_steps(scan, zenoh_socket):
    lost = {30, 31, 32, 77}
    config = ReconstructConfig(provisional=False, recovery_attempts=2, recovery_interval=0.2)
    with Rig(zenoh_socket, config, RecoveryConfig(query_timeout=0.5)) as rig:
        service = rig.start_reconstructor()
        # Lost on the way AND missing from the log (e.g. the log of another acquirer instance).
        rig.acquirer("rig").send(scan, unpublished=lost | {50}, unrecorded=lost)
        assert rig.done.wait(30), f"no terminal estimate; stats {service.stats_dict()}"
    (est,) = rig.terminal
    assert wire.status_name(est) == "incomplete"
    assert list(est.missing_steps) == sorted(lost)
    assert accounting(est) == (STEPS, STEPS - 5, 1, 0, {}, len(lost))
    assert est.samples_used == STEPS - len(lost)
    assert service.stats.incomplete == 1 and service.stats.recovery_requests >= 2


def test_late_reconstructor_catches_up_on_a_scan_in_progress(scan, zenoh_socket):
    head = 1 + 45  # ScanStart and steps 0..44 go out before the reconstructor exists
    with Rig(zenoh_socket) as rig:
        acq = rig.acquirer("rig")
        acq.send(scan[:head])
        rig.start_reconstructor()
        acq.send(scan[head:])
        assert rig.done.wait(30), f"no terminal estimate; stats {rig.service.stats_dict()}"
    (final,) = rig.terminal
    assert wire.status_name(final) == "final"
    assert accounting(final) == (STEPS, STEPS - 45, 45, 0, {}, 0)
    assert estimate_only(final) == estimate_only(replayed_final(scan))


def test_reconstructor_started_after_the_last_sample_recovers_the_whole_scan_from_its_scan_end(scan, zenoh_socket):
    with Rig(zenoh_socket) as rig:
        acq = rig.acquirer("rig")
        acq.send(scan[:-1])
        rig.start_reconstructor()
        acq.send(scan[-1:])
        assert rig.done.wait(30), f"no terminal estimate; stats {rig.service.stats_dict()}"
    (final,) = rig.terminal
    assert wire.status_name(final) == "final"
    assert accounting(final) == (STEPS, 0, STEPS, 0, {}, 0)
    assert estimate_only(final) == estimate_only(replayed_final(scan))


def test_scan_end_lost_with_the_tail_is_recovered_after_silence(scan, zenoh_socket):
    tail = set(range(100, STEPS))
    config = ReconstructConfig(provisional=False, recovery_after=0.3, recovery_interval=0.3)
    with Rig(zenoh_socket, config) as rig:
        rig.start_reconstructor()
        rig.acquirer("rig").send(scan[:-1], unpublished=tail)
        rig.acquirer("rig").log.add(scan[-1])  # the ScanEnd is recorded, never published
        assert rig.done.wait(30), f"no terminal estimate; stats {rig.service.stats_dict()}"
    (final,) = rig.terminal
    assert wire.status_name(final) == "final"
    assert accounting(final) == (STEPS, 100, len(tail), 0, {}, 0)


def test_twenty_scanners_through_one_reconstructor_each_scan_end_right_after_its_last_sample(scan, zenoh_socket):
    n = 20
    with Rig(zenoh_socket, ReconstructConfig(), expect=n) as rig:  # provisional refits on, recovery on
        service = rig.start_reconstructor()
        acquirers = [rig.acquirer(f"s{i:02d}") for i in range(n)]
        streams = [renamed(scan, f"s{i:02d}") for i in range(n)]
        threads = [threading.Thread(target=a.send, args=(s,)) for a, s in zip(acquirers, streams)]
        for t in threads:
            t.start()
        for t in threads:
            t.join(60)
        assert rig.done.wait(90), f"{len(rig.terminal)}/{n} terminal estimates; stats {service.stats_dict()}"
    assert sorted(wire.status_name(e) for e in rig.terminal) == ["final"] * n
    assert all(accounting(e) == (STEPS, STEPS, 0, 0, {}, 0) for e in rig.terminal)  # nothing needed recovery
    assert "LateMessage" not in service.ingest.rejected and not service.ingest.rejected
    assert {e.scanner_id for e in rig.terminal} == {f"s{i:02d}" for i in range(n)}


class _FlakyService(ReconstructionService):
    """Raises a non-lelsonar exception on one payload, as a bug would."""

    def __init__(self, *a, fail_on_step: int, **kw) -> None:
        super().__init__(*a, **kw)
        self._fail_on = fail_on_step
        self.failed = 0

    def handle(self, type_name: str, payload: bytes, **kw):
        if (
            type_name == "lelsonar.v1.Sample"
            and codec.Sample.FromString(payload).step == self._fail_on
            and not self.failed
        ):
            self.failed += 1
            raise ZeroDivisionError("injected")
        return super().handle(type_name, payload, **kw)


def test_live_source_worker_survives_an_unexpected_exception(scan, zenoh_socket):
    with Rig(zenoh_socket) as rig:
        svc = rig.start_reconstructor(_FlakyService(rig.config, publish=rig.collect, fail_on_step=10))
        rig.acquirer("rig").send(scan)
        assert rig.done.wait(30), f"no terminal estimate; stats {svc.stats_dict()}"
    assert svc.failed == 1
    assert rig.live.errors == 1 and rig.live.error_types == {"ZeroDivisionError": 1}
    (final,) = rig.terminal
    assert wire.status_name(final) == "final"
    assert accounting(final) == (STEPS, STEPS - 1, 1, 0, {}, 0)  # step 10 came back from the log


def test_recovery_replies_are_checked_against_the_key_and_the_request(scan, zenoh_socket):
    """A queryable that answers wrongly (another scan, a step not asked, garbage, a wildcard key)
    gets only its one good reply through; the rest is counted by reason."""
    import zenoh

    from lelsonar.keys import ScannerKeys
    from lelsonar.net.transport import ZenohSettings, open_session
    from lelsonar.reconstruct.stream.recovery import LogRecoveryClient, RecoveryRequest

    keys = ScannerKeys("lelsonar", "rig")
    good = scan[1 + 5]
    other_scan = codec.Sample()
    other_scan.CopyFrom(good)
    other_scan.scan_id = 99
    enc = zenoh.Encoding(codec.encoding_name(codec.Sample()))

    def answer(query: zenoh.Query) -> None:
        key = keys.log(42)
        query.reply(key, good.SerializeToString(), encoding=enc)  # asked: step 5
        query.reply(key, other_scan.SerializeToString(), encoding=enc)  # another scan's payload
        query.reply(key, scan[1 + 50].SerializeToString(), encoding=enc)  # step 50 was not asked
        query.reply(key, b"\x08\x01garbage", encoding=enc)  # does not decode
        query.reply(key, scan[0].SerializeToString(), encoding=enc)  # one reply too many

    delivered: list[tuple[str, bytes, str]] = []
    with open_session(ZenohSettings(mode="peer", connect=(), listen=())) as session:  # isolated
        queryable = session.declare_queryable(keys.log("*"), answer)
        with LogRecoveryClient(
            session, ScannerKeys("lelsonar", "*"), lambda *a: delivered.append(a), RecoveryConfig(query_timeout=1.0)
        ) as client:
            assert client.request(RecoveryRequest("rig", 42, steps=(4, 5, 6, 7)))  # at most 4 replies taken
            assert client.wait_idle(10)
        queryable.undeclare()
    assert delivered == [("lelsonar.v1.Sample", good.SerializeToString(), "recovered")]
    assert client.stats["rejected: identity mismatch"] == 1 and client.stats["rejected: step not asked"] == 1
    assert (
        client.stats["rejected: DecodeError"]
        + client.stats["rejected: InvalidMessageError"]
        + client.stats["rejected: SchemaVersionError"]
        == 1
    )
    assert client.stats["rejected: unexpected type"] == 0 and client.stats["rejected: more replies than asked"] == 1


def test_payload_fifo_keeps_order_bounds_what_waits_and_wakes_a_blocked_producer():
    from lelsonar.errors import ConfigError
    from lelsonar.reconstruct.stream.sources import PayloadFifo

    fifo = PayloadFifo(4, batch=3)
    assert all(fifo.put(i, timeout=0) for i in range(4))
    assert not fifo.put(4, timeout=0.01) and len(fifo) == 4  # full: refused after the timeout, nothing lost
    put_done = threading.Event()
    producer = threading.Thread(target=lambda: fifo.put(4, timeout=120) and put_done.set())
    producer.start()
    assert fifo.take(1.0) == [0, 1, 2]  # at most one batch, oldest first
    assert put_done.wait(30)  # the blocked producer was woken by the take, not by its timeout
    producer.join(30)
    assert fifo.take(1.0) == [3, 4] and fifo.take(0.01) == [] and len(fifo) == 0
    with pytest.raises(ConfigError):
        PayloadFifo(0)


def test_one_subscription_covers_both_live_keys_and_no_other_key_of_the_contract():
    # One subscriber (one channel) keeps the order across samples and scan events; the planes the
    # reconstructors publish, the tokens and the log queryables must not come back through it.
    import zenoh

    from lelsonar.keys import ScannerKeys
    from lelsonar.reconstruct.stream.sources import live_key

    for scanner in ("*", "rig"):
        ke = zenoh.KeyExpr(live_key(ScannerKeys("robot7/lelsonar", scanner)))
        one = ScannerKeys("robot7/lelsonar", "rig")
        assert ke.intersects(one.sample) and ke.intersects(one.scan)
        assert not any(
            ke.intersects(k)
            for k in (one.planes, one.alive("reconstruct"), one.log(3), "robot7/lelsonar/_group/g/done")
        )
    assert not zenoh.KeyExpr(live_key(ScannerKeys("lelsonar", "rig"))).intersects(ScannerKeys("lelsonar", "x").sample)
