"""reconstruct --group: rendezvous assignment (pure, hypothesis), two members over a Zenoh router (each
scanner's final exactly once), and a member killed mid-scan (its scans still get one complete final)."""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import threading
from collections import Counter
from contextlib import ExitStack

import pytest
import zenoh
from hypothesis import given, settings
from hypothesis import strategies as st

from lelsonar import codec
from lelsonar.errors import ConfigError, InvalidIdentifierError
from lelsonar.keys import ScannerKeys
from lelsonar.net.transport import ZenohSettings, open_session
from lelsonar.reconstruct.estimate import wire
from lelsonar.reconstruct.stream.config import ReconstructConfig
from lelsonar.reconstruct.stream.group import (
    GroupConfig,
    GroupMembership,
    eligible,
    finals_key,
    group_keys,
    owner,
)
from lelsonar.reconstruct.stream.recovery import RecoveryConfig
from lelsonar.reconstruct.stream.service import ReconstructionService
from lelsonar.reconstruct.stream.sources import LiveSource, PlanesServer

from .conftest import simulated_messages
from .live_rig import PREFIX, Acquirer, renamed

ids = st.text(alphabet="abcdefghijklmnopqrstuvwxyz0123456789-", min_size=1, max_size=12).filter(
    lambda s: s[0].isalnum()
)


# --- assignment as a pure function -----------------------------------------------------------
@settings(max_examples=60, deadline=None)
@given(scanners=st.sets(ids, min_size=1, max_size=60), members=st.sets(ids, min_size=1, max_size=8), newcomer=ids)
def test_each_scanner_has_one_owner_and_a_change_moves_only_that_members_share(scanners, members, newcomer):
    before = {s: owner(s, members) for s in scanners}
    assert all(before[s] in members for s in scanners)
    assert before == {s: owner(s, sorted(members, reverse=True)) for s in scanners}  # order does not matter
    if newcomer not in members:
        after = {s: owner(s, members | {newcomer}) for s in scanners}
        # A joining member takes scanners only for itself; nobody else's share moves.
        assert all(after[s] == before[s] for s in scanners if after[s] != newcomer)
    if len(members) > 1:
        gone = sorted(members)[0]
        after = {s: owner(s, members - {gone}) for s in scanners}
        # A leaving member's scanners move; nobody else's.
        assert all(after[s] == before[s] for s in scanners if before[s] != gone)


@settings(max_examples=20, deadline=None)
@given(members=st.sets(ids, min_size=2, max_size=6), salt=ids)
def test_assignment_is_balanced_within_the_binomial_bound(members, salt):
    # Each of n scanners goes to a member with probability 1/m (independent hashes): a member's share is
    # Binomial(n, 1/m); 6 standard deviations bound it for every member, every example (p < 1e-8 each).
    n, m = 600, len(members)
    share = Counter(owner(f"{salt}-{i}", members) for i in range(n))
    mean, sd = n / m, math.sqrt(n * (1 / m) * (1 - 1 / m))
    assert all(abs(share[x] - mean) <= 6 * sd for x in members), (share, mean, sd)


def test_owner_is_stable_across_processes_and_refuses_an_empty_group():
    out = subprocess.run(
        [
            sys.executable,
            "-c",
            "from lelsonar.reconstruct.stream.group import owner;print(owner('scanner-7', ['a', 'b', 'c']))",
        ],
        capture_output=True,
        text=True,
        env={**os.environ, "PYTHONHASHSEED": "123"},
        check=True,
    )
    assert out.stdout.strip() == owner("scanner-7", ["a", "b", "c"])
    with pytest.raises(ConfigError, match="group is empty"):
        owner("s1", [])


def test_handover_rule_joining_members_wait_for_scans_that_start_after_they_settled():
    members = {"old": 0, "new": 10_000}
    assert eligible(members, 5_000, "old", settle_ns=1_000) == ["old"]  # started before new joined
    assert eligible(members, 10_500, "new", settle_ns=1_000) == ["old"]  # within new's settle time
    assert sorted(eligible(members, 11_000, "old", settle_ns=1_000)) == ["new", "old"]
    assert eligible(members, None, "new", settle_ns=1_000) == ["old"]  # new never saw it start
    assert eligible({"solo": 5}, None, "solo", settle_ns=1_000) == ["solo"]  # alone: catch up from the log
    assert sorted(eligible(members, 100, "old", settle_ns=1_000_000)) == ["new", "old"]  # nobody settled: all


def test_group_config_is_validated_and_names_the_flag():
    with pytest.raises(InvalidIdentifierError, match="--group"):
        GroupConfig(group="a/b")
    with pytest.raises(InvalidIdentifierError, match="member id"):
        GroupConfig(group="g", member_id="*")
    with pytest.raises(ConfigError, match="--group-settle"):
        GroupConfig(group="g", settle=-1)
    assert GroupConfig(group="g").member_id != GroupConfig(group="g").member_id  # unique by default


def test_the_reconstruct_role_may_use_the_group_keys_and_the_others_may_not():
    from lelsonar.net.secure import PLANNER, RECONSTRUCT, acquire_role, role_rules

    members, done = group_keys(PREFIX, "g")
    token = members.replace("*/*", "m1/123")
    finals = finals_key(PREFIX, "g", "m1")

    def allowed(role, message, flow, key):
        return any(
            message in r["messages"]
            and flow in r["flows"]
            and any(zenoh.KeyExpr(k).includes(zenoh.KeyExpr(key)) for k in r["key_exprs"])
            for r in role_rules(role, PREFIX)
        )

    for message, flow, key in (
        ("liveliness_token", "ingress", token),
        ("declare_liveliness_subscriber", "ingress", members),
        ("liveliness_token", "egress", token),
        ("put", "ingress", done),
        ("declare_subscriber", "ingress", done),
        ("put", "egress", done),
        ("declare_queryable", "ingress", finals),
        ("query", "ingress", finals),
        ("reply", "ingress", finals),
        ("query", "egress", finals),
        ("reply", "egress", finals),
    ):
        assert allowed(RECONSTRUCT, message, flow, key), (message, flow, key)
        assert not allowed(PLANNER, message, flow, key) and not allowed(acquire_role("s1"), message, flow, key)


def test_group_flags_come_from_the_config_file(tmp_path):
    from lelsonar.cli.config_file import parse_args
    from lelsonar.cli.main import build_parser

    path = tmp_path / "site.toml"
    path.write_text('[reconstruct]\ngroup = "site"\nmember-id = "m1"\ngroup_settle = 0.5\n')
    args = parse_args(build_parser(), ["reconstruct", "--config", str(path), "--member-id", "m2"])
    assert (args.group, args.member_id, args.group_settle) == ("site", "m2", 0.5)


# --- live, over a Zenoh router -------------------------------------------------------------------
STEPS = 120


@pytest.fixture(scope="module")
def scan():
    return simulated_messages("paper-test1", seed=3, steps=STEPS)


def scanners_split(members: list[str], per_member: int) -> list[str]:
    """Scanner ids such that each member owns ``per_member`` of them."""
    chosen: dict[str, list[str]] = {m: [] for m in members}
    i = 0
    while any(len(v) < per_member for v in chosen.values()):
        s = f"s{i}"
        i += 1
        if len(chosen[who := owner(s, members)]) < per_member:
            chosen[who].append(s)
    return sorted(sum(chosen.values(), []))


class Finals:
    """Terminal estimates seen on ``<prefix>/*/planes``, by scan."""

    def __init__(self, session: zenoh.Session, expect: int) -> None:
        self.by_scan: dict[tuple[str, int], list[codec.Reconstruction]] = {}
        self.provisional: Counter[str] = Counter()
        self.expect = expect
        self.done = threading.Event()
        self.cv = threading.Condition()
        self._sub = session.declare_subscriber(f"{PREFIX}/*/planes", self._on)

    def _on(self, sample: zenoh.Sample) -> None:
        msg = codec.Reconstruction.FromString(sample.payload.to_bytes())
        with self.cv:
            if wire.is_terminal(msg):
                self.by_scan.setdefault((msg.scanner_id, msg.scan_id), []).append(msg)
                if len(self.by_scan) >= self.expect:
                    self.done.set()
            else:
                self.provisional[msg.scanner_id] += 1
            self.cv.notify_all()


def router_settings(endpoint: str) -> ZenohSettings:
    return ZenohSettings(mode="router", listen=(endpoint,), connect=())


def client(endpoint: str) -> ZenohSettings:
    return ZenohSettings(mode="client", connect=(endpoint,))


def start_member(stack: ExitStack, endpoint: str, member: str) -> GroupMembership:
    """A reconstructor in group "g", wired as `reconstruct --group g` wires it."""
    session = stack.enter_context(open_session(client(endpoint)))
    keys = ScannerKeys(PREFIX, "*")
    group = stack.enter_context(GroupMembership(session, PREFIX, GroupConfig("g", member, settle=0.0)))
    server = None
    service = ReconstructionService(
        ReconstructConfig(provisional=False, compare_methods=()), publish=group.fenced(lambda msg: server.publish(msg))
    )
    server = PlanesServer(session, keys, service.latest, answers_for=group.answers_for)
    stack.callback(server.close)
    stop = threading.Event()
    stack.enter_context(
        LiveSource(session, keys, service, stop, recovery=RecoveryConfig(query_timeout=2.0), group=group)
    )
    group.service = service  # for the test's checks
    # Declared after the source's subscribers: once seen, the subscribers are known too.
    stack.callback(session.liveliness().declare_token(f"{PREFIX}/{member}/alive/test-member").undeclare)
    return group


def wait_subscribed(acq_session: zenoh.Session, n: int) -> None:
    """Until ``n`` sessions subscribe to every scanner's sample key (the members' sources are up)."""
    wait_alive(acq_session, f"{PREFIX}/*/alive/test-member", n)


def wait_alive(acq_session: zenoh.Session, key: str, n: int) -> None:
    """Until ``n`` liveliness tokens on ``key`` are up."""
    ready = threading.Event()
    seen: Counter[str] = Counter()
    lock = threading.Lock()

    def on_token(sample: zenoh.Sample) -> None:
        with lock:
            seen[str(sample.key_expr)] += sample.kind == zenoh.SampleKind.PUT
            if sum(seen.values()) >= n:
                ready.set()

    sub = acq_session.liveliness().declare_subscriber(key, on_token, history=True)
    assert ready.wait(30), f"members not up: {dict(seen)}"
    sub.undeclare()


def test_a_joining_member_knows_the_members_alive_before_it_judges_any_payload(tmp_path):
    # Judging before the others' tokens arrive, a newcomer would think itself alone and take
    # the payloads of a scan its elders own (a flake CI once caught): joining asks and waits.
    endpoint = f"unixsock-stream/{tmp_path}/router.sock"
    with ExitStack() as stack:
        stack.enter_context(open_session(router_settings(endpoint)))
        elders = []
        for m in ("a", "b", "c"):
            session = stack.enter_context(open_session(client(endpoint)))
            elders.append(stack.enter_context(GroupMembership(session, PREFIX, GroupConfig("g", m, settle=0.0))))
        assert all(e.wait_members(3, 20) for e in elders)
        newcomer = stack.enter_context(
            GroupMembership(
                stack.enter_context(open_session(client(endpoint))), PREFIX, GroupConfig("g", "d", settle=0.0)
            )
        )
        # No waiting here: what __enter__ returned with is what the first payload is judged by.
        assert sorted(newcomer.members) == ["a", "b", "c", "d"]
        assert newcomer.stats["members joined"] == 3
        scanner = next(s for s in (f"s{i}" for i in range(100)) if owner(s, ["a", "b", "c", "d"]) == "d")
        assert newcomer.owner_of(scanner) != "d"  # a scan it never saw start is its elders'


def test_two_members_each_scanner_final_arrives_exactly_once(tmp_path, scan):
    endpoint = f"unixsock-stream/{tmp_path}/router.sock"
    scanners = scanners_split(["a", "b"], 2)
    with ExitStack() as stack:
        stack.enter_context(open_session(router_settings(endpoint)))
        a = start_member(stack, endpoint, "a")
        b = start_member(stack, endpoint, "b")
        assert a.wait_members(2, 20) and b.wait_members(2, 20)
        acq = stack.enter_context(open_session(client(endpoint)))
        finals = Finals(acq, expect=len(scanners))
        acquirers = [Acquirer(acq, s) for s in scanners]
        for x in acquirers:
            stack.callback(x.close)
        wait_subscribed(acq, 2)  # both members' sources are up (their subscribers precede their tokens)
        for x in acquirers:
            x.send(renamed(scan, x.keys.scanner_id))
        assert finals.done.wait(40), f"finals: {sorted(finals.by_scan)}"
        # Wait for both members to finish (a duplicate would come from the other member's own final).
        assert a.service.stats.finals + b.service.stats.finals == len(scanners)
        # A get on every scanner's planes is answered once per scanner, by whichever member owns it.
        replies = [
            str(r.ok.key_expr)
            for r in acq.get(f"{PREFIX}/*/planes", timeout=5, consolidation=zenoh.ConsolidationMode.NONE)
            if r.ok
        ]
        assert sorted(replies) == [f"{PREFIX}/{s}/planes" for s in scanners]
    assert sorted(finals.by_scan) == [(s, 1) for s in scanners]
    for key, msgs in finals.by_scan.items():
        assert len(msgs) == 1, f"{key}: {len(msgs)} finals"
        assert wire.status_name(msgs[0]) == "final" and msgs[0].accounting.missing == 0
    # Each member processed its own scanners and dropped the others' before decoding, counted.
    assert a.service.stats.finals == 2 and b.service.stats.finals == 2
    assert a.stats["dropped: other member"] > 0 and b.stats["dropped: other member"] > 0
    assert not a.service.ingest.rejected and not b.service.ingest.rejected


def test_a_member_killed_mid_scan_its_scans_still_get_one_complete_final(tmp_path, scan):
    endpoint = f"unixsock-stream/{tmp_path}/router.sock"
    scanners = scanners_split(["a", "b"], 2)
    b_scanners = [s for s in scanners if owner(s, ["a", "b"]) == "b"]
    cut = 90  # past the corner: b has published provisional estimates of its scans
    with ExitStack() as stack:
        stack.enter_context(open_session(router_settings(endpoint)))
        acq = stack.enter_context(open_session(client(endpoint)))
        finals = Finals(acq, expect=len(scanners))
        proc = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "lelsonar",
                "reconstruct",
                "--group",
                "g",
                "--member-id",
                "b",
                "--group-settle",
                "0",
                "--provisional-deadline",  # (the cut arrives at once: on a loaded host all of it is late)
                "0",
                "--compare",
                "",
                "--mode",
                "client",
                "--connect",
                endpoint,
            ],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
        )
        stack.callback(lambda: proc.poll() is None and proc.kill())
        a = start_member(stack, endpoint, "a")
        assert a.wait_members(2, 30), proc.stderr.read() if proc.poll() is not None else "b never joined"
        acquirers = {s: Acquirer(acq, s) for s in scanners}
        for x in acquirers.values():
            stack.callback(x.close)
        # b's "alive" token means it listens; sent before, a whole scan's start could pass it by unheard.
        wait_alive(acq, f"{PREFIX}/*/alive/reconstruct", 1)
        messages = {s: renamed(scan, s) for s in scanners}
        for s, x in acquirers.items():
            x.send(messages[s][: 1 + cut])  # ScanStart and the first `cut` steps
        with finals.cv:
            assert finals.cv.wait_for(lambda: all(finals.provisional[s] for s in b_scanners), 40), (
                f"b published no provisional estimate: {dict(finals.provisional)}"
            )
        proc.send_signal(signal.SIGKILL)
        proc.wait(10)
        with a.changed:
            assert a.changed.wait_for(lambda: "b" not in a.members, 20)
        for s, x in acquirers.items():
            x.send(messages[s][1 + cut :])  # the rest and the ScanEnd
        assert finals.done.wait(40), f"finals: {sorted(finals.by_scan)}; group {a.stats_dict()}"
    assert sorted(finals.by_scan) == [(s, 1) for s in scanners]
    for key, msgs in finals.by_scan.items():
        assert len(msgs) == 1, f"{key}: {len(msgs)} finals"
        est = msgs[0]
        assert wire.status_name(est) == "final" and not est.missing_steps, key
        assert est.accounting.missing == 0 and est.samples_used == STEPS
    assert a.stats["scans adopted"] == len(b_scanners)
    # b's scans were completed from the acquirers' logs: every sample a dropped as b's came back from them
    # (all but b's ScanStarts, which a kept and fed itself).  Samples of b's that a's worker reached only
    # after b had gone were a's to take live.
    dropped = a.stats["dropped: other member"] - len(b_scanners)
    assert dropped > 0 and a.service.stats.recovered >= dropped


# --- the watcher's decisions, without a network ------------------------------------------------
class _Payload:
    def __init__(self, data: bytes) -> None:
        self.data = data

    def to_bytes(self) -> bytes:
        return self.data


class _Sample:
    def __init__(self, key: str, kind=zenoh.SampleKind.PUT, payload: bytes = b"") -> None:
        self.key_expr, self.kind, self.payload = key, kind, _Payload(payload)


def _watcher(me: str, others: dict[str, int]) -> tuple[GroupMembership, list]:
    group = GroupMembership(None, PREFIX, GroupConfig("g", me, settle=0.0), clock_ns=lambda: 0)
    fed: list = []
    group.attach(lambda enc, payload, origin, scanner: fed.append((enc.rpartition(".")[2], scanner, origin)))
    group._done_pub = type("P", (), {"put": lambda self, data: None})()
    for m, joined in others.items():
        group._on_token(_Sample(f"{PREFIX}/_group/g/member/{m}/{joined}"))
    return group, fed


def _scan_msgs(scanner: str):
    msgs = renamed(simulated_messages("paper-test1", seed=1, steps=8), scanner)
    return msgs[0], msgs[-1]


def test_a_dead_members_ended_scan_without_a_final_is_adopted_and_one_with_a_final_is_not():
    group, fed = _watcher("a", {"b": 0})
    b_owned = [s for s in (f"s{i}" for i in range(40)) if owner(s, ["a", "b"]) == "b"][:2]
    for s in b_owned:
        start, end = _scan_msgs(s)
        for m in (start, end):
            assert not group.admit(s, "scan", codec.encoding_name(m), _Payload(m.SerializeToString()))
        assert not group.admit(s, "sample", "", None)
    assert group.stats["dropped: other member"] == 6
    # b published the final of the first scanner's scan (its done mark came), then died.
    group._on_done(_Sample(f"{PREFIX}/_group/g/done", payload=f"{b_owned[0]}/1".encode()))
    group._on_token(_Sample(f"{PREFIX}/_group/g/member/b/0", zenoh.SampleKind.DELETE))
    assert group.members == {"a": 0}
    # Only the scan without a final is adopted: its kept ScanStart and ScanEnd go to the source.
    assert fed == [("ScanStart", b_owned[1], "live"), ("ScanEnd", b_owned[1], "live")]
    assert group.stats["scans adopted"] == 1
    assert group.admit(b_owned[1], "sample", "", None) and group.answers_for(b_owned[0])


def test_a_departed_members_scans_reach_a_full_fifo_while_its_worker_asks_the_fence():
    # The live source's FIFO is full and its worker asks may_publish (the group's lock) before it takes
    # the next batch.  Feeding the adopted scan's kept messages while holding that lock made each wait
    # for the other: the feeder for room, the worker for the lock.
    from lelsonar.reconstruct.stream.sources import PayloadFifo

    group, _ = _watcher("a", {"b": 0})
    s = next(s for s in (f"s{i}" for i in range(40)) if owner(s, ["a", "b"]) == "b")
    start, end = _scan_msgs(s)
    for m in (start, end):
        assert not group.admit(s, "scan", codec.encoding_name(m), _Payload(m.SerializeToString()))
    fifo = PayloadFifo(1)
    assert fifo.put(("live", None), timeout=0)  # full
    feeding, asked = threading.Event(), threading.Event()

    def enqueue(encoding, payload, origin, scanner):  # as the live source's: waits for room
        feeding.set()
        fifo.put(
            (codec.MESSAGE_TYPES[encoding.partition(";")[2]].FromString(payload).DESCRIPTOR.name, scanner), timeout=30
        )  # bounded, so that a deadlock fails the test instead of hanging it

    taken: list = []

    def worker():
        assert feeding.wait(30)
        group.may_publish(_final(s, start.scan_id, "provisional"))
        asked.set()
        while len(taken) < 3 and (more := fifo.take(30)):
            taken.extend(more)

    group.attach(enqueue)
    threads = [
        threading.Thread(target=worker, daemon=True),
        threading.Thread(
            target=group._on_token,
            daemon=True,
            args=(_Sample(f"{PREFIX}/_group/g/member/b/0", zenoh.SampleKind.DELETE),),
        ),
    ]
    for t in threads:
        t.start()
    assert asked.wait(10), "the worker waited for the group's lock while the adopted scan waited for room"
    for t in threads:
        t.join(30)
    assert taken == [("live", None), ("ScanStart", s), ("ScanEnd", s)]  # nothing lost, in order
    assert group.stats["scans adopted"] == 1 and group.owner_of(s) == "a"


def test_a_member_that_joins_mid_scan_leaves_that_scan_to_its_owner_and_takes_the_next():
    old, _ = _watcher("old", {})
    old.joined_ns = 0
    s = next(s for s in (f"s{i}" for i in range(40)) if owner(s, ["old", "new"]) == "new")
    start, _end = _scan_msgs(s)
    start.start_time_ns = 1_000
    assert old.admit(s, "scan", codec.encoding_name(start), _Payload(start.SerializeToString()))
    old._on_token(_Sample(f"{PREFIX}/_group/g/member/new/2000"))  # joins mid-scan
    assert old.admit(s, "sample", "", None)  # old keeps the scan it started
    nxt = codec.ScanStart()
    nxt.CopyFrom(start)
    nxt.scan_id, nxt.start_time_ns = 2, 3_000
    assert not old.admit(s, "scan", codec.encoding_name(nxt), _Payload(nxt.SerializeToString()))  # the next: new's
    assert not old.admit(s, "sample", "", None)
    # The same member id from another process is a conflict, reported.
    old._on_token(_Sample(f"{PREFIX}/_group/g/member/old/5"))
    assert old.stats["conflict: member id used by another process"] == 1
    # Malformed tokens and marks are counted, never raised into Zenoh's thread.
    old._on_token(_Sample(f"{PREFIX}/_group/g/member/x*y/zz"))
    old._on_done(_Sample(f"{PREFIX}/_group/g/done", payload=b"\xff"))
    assert old.stats["rejected: malformed member token"] == 1 and old.stats["rejected: malformed done mark"] == 1


def _final(scanner: str, scan_id: int, status: str = "final") -> codec.Reconstruction:
    from lelsonar.reconstruct.estimate.wire import STATUS

    return codec.Reconstruction(scanner_id=scanner, scan_id=scan_id, status=STATUS[status])


def test_after_a_healed_partition_the_scans_taken_from_a_member_go_back_to_it_and_are_fenced():
    # The partition looked like a death: a adopted b's scan.  b's token returns unchanged (the same process).
    group, fed = _watcher("a", {"b": 7})
    s = next(s for s in (f"s{i}" for i in range(40)) if owner(s, ["a", "b"]) == "b")
    start, _end = _scan_msgs(s)
    assert not group.admit(s, "scan", codec.encoding_name(start), _Payload(start.SerializeToString()))
    group._on_token(_Sample(f"{PREFIX}/_group/g/member/b/7", zenoh.SampleKind.DELETE))
    assert group.stats["scans adopted"] == 1 and group.may_publish(_final(s, start.scan_id, "provisional"))
    group._on_token(_Sample(f"{PREFIX}/_group/g/member/b/7"))
    assert group.stats["scans handed back"] == 1 and not group.admit(s, "sample", "", None)
    # What a computed of it before the heal is not published: b owns the scan again.
    assert not group.may_publish(_final(s, start.scan_id))
    assert not group.may_publish(_final(s, start.scan_id, "provisional"))
    assert group.stats["fenced: estimate of a scan another member owns"] == 2
    # A restarted b (another token) is a new member: what a adopted stays a's.
    other, _ = _watcher("a", {"b": 7})
    assert not other.admit(s, "scan", codec.encoding_name(start), _Payload(start.SerializeToString()))
    other._on_token(_Sample(f"{PREFIX}/_group/g/member/b/7", zenoh.SampleKind.DELETE))
    other._on_token(_Sample(f"{PREFIX}/_group/g/member/b/9"))
    assert other.stats["scans handed back"] == 0
    other._published_elsewhere = lambda scanner, scan_id: False  # no network here: nobody else published it
    assert other.may_publish(_final(s, start.scan_id))


def test_a_final_another_member_published_while_its_mark_was_lost_is_fenced(tmp_path):
    endpoint = f"unixsock-stream/{tmp_path}/router.sock"
    with ExitStack() as stack:
        stack.enter_context(open_session(router_settings(endpoint)))

        def member(m: str) -> GroupMembership:
            session = stack.enter_context(open_session(client(endpoint)))
            return stack.enter_context(GroupMembership(session, PREFIX, GroupConfig("g", m, settle=0.0)))

        a = member("a")
        s = next(s for s in (f"s{i}" for i in range(40)) if owner(s, ["a", "b"]) == "b")
        start, _end = _scan_msgs(s)
        a.on_estimate(_final(s, start.scan_id))  # published while b was cut off: b never gets the mark
        b = member("b")
        assert b.wait_members(2, 20)
        assert b.admit(s, "scan", codec.encoding_name(start), _Payload(start.SerializeToString()))  # b's scan
        asked: list = []
        ask = b._published_elsewhere
        b._published_elsewhere = lambda *key: asked.append(key) or ask(*key)
        # A member that joins, or dies, tells b nothing about its finals: no question (a dead member's
        # queryable would hold the question until its lease ran out).
        member("c")
        assert b.wait_members(3, 20)
        other = codec.ScanStart()
        other.CopyFrom(start)
        other.scanner_id = next(x for x in (f"t{i}" for i in range(40)) if owner(x, ["a", "b", "c"]) == "b")
        assert b.admit(other.scanner_id, "scan", codec.encoding_name(other), _Payload(other.SerializeToString()))
        assert b.may_publish(_final(other.scanner_id, other.scan_id)) and asked == []
        # a's token goes and comes back unchanged, as b sees a partition heal: now b asks, and holds back.
        token = f"{PREFIX}/_group/g/member/a/{a.joined_ns}"
        b._on_token(_Sample(token, zenoh.SampleKind.DELETE))
        b._on_token(_Sample(token))
        assert not b.may_publish(_final(s, start.scan_id)) and asked == [(s, start.scan_id)]
        assert b.stats["fenced: final another member already published"] == 1
        # A scan that began after the return asks nothing and goes out.
        nxt = codec.ScanStart()
        nxt.CopyFrom(start)
        nxt.scan_id += 1
        assert b.admit(s, "scan", codec.encoding_name(nxt), _Payload(nxt.SerializeToString()))
        assert b.may_publish(_final(s, nxt.scan_id)) and len(asked) == 1


def test_under_a_backlog_an_ended_scans_recovery_neither_retries_nor_gives_up(scan):
    """A member that adopted many scans is behind: the replies to its requests wait in its queue."""
    from lelsonar.reconstruct.stream.recovery import RecoveryRequest

    now = [0.0]
    asked: list[RecoveryRequest] = []
    service = ReconstructionService(
        ReconstructConfig(provisional=False, compare_methods=(), recovery_attempts=2, recovery_interval=0.5),
        clock=lambda: now[0],
        recover=lambda r: asked.append(r) or True,
    )
    for m in scan:
        if not (isinstance(m, codec.Sample) and m.step < 50):
            service.handle(m.DESCRIPTOR.full_name, m.SerializeToString())
    assert len(asked) == 1  # at the ScanEnd
    for t in range(1, 40):
        now[0] = t
        assert service.tick(busy=True) == []
    assert len(asked) == 1
    for m in scan[1:51]:  # the replies, once the backlog is through
        service.handle(m.DESCRIPTOR.full_name, m.SerializeToString(), origin="recovered")
    (final,) = [e for e in service.tick() if wire.is_terminal(e)] or [service.finals[("s1", 1)]]
    assert wire.status_name(final) == "final" and final.accounting.recovered == 50


def test_a_member_that_joins_mid_scan_takes_its_share_at_the_next_scan(tmp_path, scan):
    import time

    endpoint = f"unixsock-stream/{tmp_path}/router.sock"
    scanners = scanners_split(["a", "b", "c"], 1)
    first = {s: renamed(scan, s) for s in scanners}
    second = {}
    for s in scanners:
        msgs = renamed(scan, s)
        for m in msgs:
            m.scan_id = 2
        second[s] = msgs
    with ExitStack() as stack:
        stack.enter_context(open_session(router_settings(endpoint)))
        a = start_member(stack, endpoint, "a")
        b = start_member(stack, endpoint, "b")
        assert a.wait_members(2, 20) and b.wait_members(2, 20)
        acq = stack.enter_context(open_session(client(endpoint)))
        finals = Finals(acq, expect=2 * len(scanners))
        acquirers = {s: Acquirer(acq, s) for s in scanners}
        for x in acquirers.values():
            stack.callback(x.close)
        wait_subscribed(acq, 2)
        for s, x in acquirers.items():
            # The scan starts now, after a and b joined and before c does: its owner is one of a and b
            # whenever a member gets to its ScanStart (a start before every member joined would be
            # shared among the members known then, which a backlogged member may learn later).
            first[s][0].start_time_ns = time.time_ns()
            x.send(first[s][: 1 + STEPS // 2])
        c = start_member(stack, endpoint, "c")  # joins mid-scan
        assert all(m.wait_members(3, 20) for m in (a, b, c))
        wait_subscribed(acq, 3)
        for s, x in acquirers.items():
            x.send(first[s][1 + STEPS // 2 :])
        for s, x in acquirers.items():
            second[s][0].start_time_ns = time.time_ns()  # after c joined (settle 0): c takes part
            x.send(second[s])
        assert finals.done.wait(40), f"finals: {sorted(finals.by_scan)}"
        with finals.cv:
            assert finals.cv.wait_for(
                lambda: a.service.stats.finals + b.service.stats.finals + c.service.stats.finals == 2 * len(scanners),
                10,
            )
    assert all(len(v) == 1 and wire.status_name(v[0]) == "final" for v in finals.by_scan.values())
    assert sorted(finals.by_scan) == sorted((s, k) for s in scanners for k in (1, 2))
    # c left the scans that had started to their owners, and took its share of the next ones.
    assert {m.scan_id for m in c.service.finals.values()} == {2} and c.service.stats.finals == 1
    assert a.service.stats.finals + b.service.stats.finals == 2 * len(scanners) - 1
