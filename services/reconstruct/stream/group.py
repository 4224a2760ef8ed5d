"""Reconstructors that share the scanners of a prefix: ``lelsonar reconstruct --group NAME``.

No coordinator: each member declares a liveliness token and watches the
others'; every member computes the same assignment from the same facts.

Assignment (pure, :func:`owner`): rendezvous (highest-random-weight) hashing.
A scanner belongs to the member with the highest ``blake2b(member, scanner)``.
Adding a member moves only the scanners it now wins; removing one moves only
the scanners it owned; each member gets about ``scanners / members``.

Which members a scan is assigned among (:func:`eligible`) — the handover rule:

- **A scan is assigned once, at its ScanStart, and its owner keeps it until
  that scan's final.**  Hand over happens only between scans.
- A member that joined at ``joined_ns`` (its own clock, in its token) takes
  part in the scans that start (``ScanStart.start_time_ns``, the acquirer's
  clock) at least ``settle`` seconds later, so every member has seen its token
  before such a scan starts and all agree.  Clocks must agree within
  ``settle`` (NTP).  If no member qualifies, all alive members do — the
  members known when this member handles the ScanStart, which a member with
  a backlog handles later than the others: a member joining meanwhile can be
  counted by one and not by another.  That happens only for scans that start
  within ``settle`` of the oldest member joining (or with clocks further apart).
- A scan whose ScanStart a member never saw (it joined mid-scan) is assigned
  among the members older than it (they saw the start); with none, to itself
  (it catches up from the acquirer's log, as a lone reconstructor does).
- **When a member leaves or dies** (its token disappears), each of its scans
  without a final is reassigned among the members left.  The new owner is
  fed the ScanStart and ScanEnd it kept, takes the scanner's samples from then
  on, and asks the acquirer's log for the rest
  (:mod:`lelsonar.reconstruct.stream.recovery`), so the scan still gets one final.
  A member marks each final it publishes on ``<prefix>/_group/<group>/done``;
  a scan marked done is never adopted (no second final).

The fence (after a partition, both sides believe the other dead and adopt its
scans): a member publishes an estimate only of a scan it owns now
(:meth:`GroupMembership.may_publish`).  When a member it had given up for gone
comes back (the same token: the same process, a healed partition), the
unfinished scans taken from it are handed back.  And before the final of a
scan during which such a member came back, the member asks the others'
tables of published finals (a ``get``; the done marks sent during a partition
were lost) and publishes only if no other member has.  Estimates of a scan
are the same whoever computes them (the final is a replay of the log), so what
the fence prevents is a second final, not a different one.

Keys: ``<prefix>/_group/<group>/member/<member_id>/<joined_ns>`` (liveliness),
``<prefix>/_group/<group>/done`` (payload ``<scanner>/<scan_id>``) and
``<prefix>/_group/<group>/finals/<member_id>`` (queryable: ``?scanner=S;scan=N``
is answered ``done`` if that member published the scan's final).

Payloads of scanners a member does not own are dropped by the live source's
worker before decoding (the scanner id is in the key), and counted as "other
member".  ScanStart / ScanEnd of every scanner are decoded (they are small)
to follow which scan is whose.
"""

from __future__ import annotations

import hashlib
import logging
import os
import socket
import threading
import time
from collections import Counter, OrderedDict
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field

import zenoh

from lelsonar import codec
from lelsonar.errors import ConfigError, InvalidIdentifierError
from lelsonar.keys import validate_identifier, validate_prefix
from lelsonar.reconstruct.estimate import wire

_log = logging.getLogger(__name__)

GROUP_CHUNK = "_group"
OTHER_MEMBER = "other member"


# --- the pure part -----------------------------------------------------------------------
def weight(scanner_id: str, member: str) -> int:
    """The rendezvous weight of (scanner, member): a stable 64-bit hash (never Python's salted hash())."""
    h = hashlib.blake2b(f"{member}\x00{scanner_id}".encode(), digest_size=8)
    return int.from_bytes(h.digest(), "big")


def owner(scanner_id: str, members: Iterable[str]) -> str:
    """The member that processes ``scanner_id``: the highest weight (ties: the greatest member id).

    Raises
    ------
    ConfigError
        With no member at all (a group always holds at least the caller).
    """
    best = max(members, key=lambda m: (weight(scanner_id, m), m), default=None)
    if best is None:
        raise ConfigError(
            f"no member to own scanner {scanner_id!r}: the group is empty (is this member's own token declared?)"
        )
    return best


def eligible(members: Mapping[str, int], start_ns: int | None, me: str, settle_ns: int) -> list[str]:
    """The members a scan is assigned among (see the module's handover rule).

    ``members``: member id → joined_ns, the caller included; ``start_ns``: the scan's
    ``ScanStart.start_time_ns``, or None if the caller never saw its ScanStart.
    """
    if start_ns is not None:
        chosen = [m for m, j in members.items() if j + settle_ns <= start_ns]
        return chosen or list(members)
    mine = (members[me], me)
    return [m for m, j in members.items() if (j, m) < mine] or [me]


def default_member_id() -> str:
    """A unique, key-safe member id: host, pid and random bits."""
    host = "".join(c if c.isalnum() or c in "_.-" else "-" for c in socket.gethostname())[:24].strip("-._")
    return f"{host or 'host'}-{os.getpid()}-{os.urandom(3).hex()}"


@dataclass(frozen=True)
class GroupConfig:
    """One member of a group.

    Parameters
    ----------
    group : str
        The group's name (a key chunk).
    member_id : str
        Unique within the group (default: host-pid-random).
    settle : float
        s; a joining member takes part in scans starting this long after it joined.
    max_members : int
        Members tracked; more tokens are ignored (counted).
    max_scanners : int
        Scanners followed; the least recently heard is forgotten (counted).
    keep_scans : int
        Scans followed per scanner (a backlogged owner may still hold older ones).
    join_timeout : float
        s; how long joining waits for the members alive to answer, and the fence for the
        others' tables of finals.
    keep_finals : int
        Finals remembered (and answered for) in this member's table.
    """

    group: str
    member_id: str = field(default_factory=default_member_id)
    settle: float = 2.0
    max_members: int = 64
    max_scanners: int = 1024
    keep_scans: int = 4
    join_timeout: float = 5.0
    keep_finals: int = 4096

    def __post_init__(self) -> None:
        try:
            validate_identifier(self.group, what="group name")
            validate_identifier(self.member_id, what="member id")
        except InvalidIdentifierError as exc:
            raise InvalidIdentifierError(f"{exc} (reconstruct --group NAME / --member-id ID)") from None
        if not self.settle >= 0:
            raise ConfigError(f"group settle must be >= 0 s, got {self.settle} (reconstruct --group-settle S)")
        if not self.join_timeout > 0:
            raise ConfigError(f"group join_timeout must be > 0 s, got {self.join_timeout}")
        if min(self.max_members, self.max_scanners, self.keep_scans, self.keep_finals) < 1:
            raise ConfigError("group max_members, max_scanners, keep_scans and keep_finals must be >= 1")


def group_keys(prefix: str, group: str) -> tuple[str, str]:
    """(member token wildcard, done key) of a group."""
    base = f"{validate_prefix(prefix)}/{GROUP_CHUNK}/{validate_identifier(group, what='group name')}"
    return f"{base}/member/*/*", f"{base}/done"


def finals_key(prefix: str, group: str, member: str = "*") -> str:
    """The key of a member's table of published finals (``*``: every member's)."""
    return group_keys(prefix, group)[1].removesuffix("/done") + f"/finals/{member}"


@dataclass
class _Scan:
    """What a member knows of one scan of a scanner, whoever owns it."""

    owner: str
    start_ns: int | None = None
    start: tuple[str, bytes] | None = None  # (encoding, payload) as received
    end: tuple[str, bytes] | None = None
    done: bool = False
    returns: int = 0  # members seen back from a partition when the scan was first heard of
    taken_from: str | None = None  # the member it was adopted from (handed back if that one returns)


# --- the Zenoh part ----------------------------------------------------------------------
class GroupMembership:
    """Declares this member, watches the others, and says which payloads are this member's.

    Use as a context manager inside an open session, around the
    :class:`~lelsonar.reconstruct.stream.sources.LiveSource` it filters (the source's worker calls
    :meth:`admit` for every live payload, and the source calls :meth:`attach` on start).
    """

    def __init__(
        self, session: zenoh.Session, prefix: str, config: GroupConfig, *, clock_ns: Callable[[], int] = time.time_ns
    ) -> None:
        self.config = config
        self.me = config.member_id
        self.prefix = validate_prefix(prefix)
        self._session = session
        self._settle_ns = int(config.settle * 1e9)
        self.joined_ns = clock_ns()
        self._lock = threading.RLock()
        self.members: dict[str, int] = {self.me: self.joined_ns}
        self._scans: OrderedDict[str, OrderedDict[int | None, _Scan]] = OrderedDict()
        self._enqueue: Callable[[str, bytes, str, str | None], None] | None = None
        self.changed = threading.Condition(self._lock)
        #: Dropped payloads, adoptions, membership changes, refusals and evictions, by name.
        self.stats: Counter[str] = Counter()
        self._member_key, self._done_key = group_keys(prefix, config.group)
        self._token_key = self._member_key.replace("*/*", f"{self.me}/{self.joined_ns}")
        self._finals_key = finals_key(prefix, config.group, self.me)
        self._entities: list = []
        #: Members seen come back with the token they left with (healed partitions) so far.
        self._returns = 0
        #: Members given up for gone, with the token they had (bounded like the members).
        self._departed: OrderedDict[str, int] = OrderedDict()
        #: The finals this member published: (scanner, scan_id), oldest first.
        self._published: OrderedDict[tuple[str, int], None] = OrderedDict()

    # --- lifecycle ---
    def __enter__(self) -> GroupMembership:
        s = self._session
        self._done_pub = s.declare_publisher(self._done_key)
        self._entities.append(self._done_pub)
        self._entities.append(s.declare_subscriber(self._done_key, self._on_done))
        self._entities.append(s.declare_queryable(self._finals_key, self._answer_finals))
        # Asked before this session declares anything on the member keys: with its own token or
        # liveliness subscriber already there, the query was seen to end at once, unanswered.
        self._learn_members()
        self._entities.append(s.liveliness().declare_subscriber(self._member_key, self._on_token, history=True))
        self._entities.append(s.liveliness().declare_token(self._token_key))
        return self

    def _learn_members(self) -> None:
        """Ask for the members alive now, and wait for the answer, before any payload is judged.

        The subscriber's history arrives in the background; a member that judged payloads
        before it would think itself alone and take scans that are its elders'.
        """
        try:
            replies = self._session.liveliness().get(self._member_key, timeout=self.config.join_timeout)
            for reply in replies:
                if reply.ok is not None:
                    self._on_token(reply.ok)
        except zenoh.ZError as exc:
            self.stats["errors: member query"] += 1
            _log.warning(
                "group %s: the members alive could not be asked (%s); relying on their tokens as they arrive",
                self.config.group,
                exc,
            )

    def __exit__(self, *exc_info) -> None:
        self.close()

    def close(self) -> None:
        for e in reversed(self._entities):
            try:
                e.undeclare()
            except zenoh.ZError:  # the session is already closed
                pass
        self._entities.clear()

    def attach(self, enqueue: Callable[[str, bytes, str, str | None], None] | None) -> None:
        """Where adopted scans' kept messages go (the live source's queue); None detaches."""
        with self._lock:
            self._enqueue = enqueue

    def wait_members(self, n: int, timeout: float) -> bool:
        """Wait until ``n`` members (this one included) are known; False on timeout."""
        with self.changed:
            return self.changed.wait_for(lambda: len(self.members) >= n, timeout)

    # --- ownership ---
    def owner_of(self, scanner: str) -> str:
        """Who processes the scanner's newest scan, as far as this member knows."""
        with self._lock:
            scans = self._scans.get(scanner)
            if scans:
                return next(reversed(scans.values())).owner
            return owner(scanner, eligible(self.members, None, self.me, self._settle_ns))

    def answers_for(self, scanner: str) -> bool:
        """Whether a ``get`` on planes should answer for ``scanner`` here (its current owner does)."""
        return self.owner_of(scanner) == self.me

    def admit(self, scanner: str, leaf: str, encoding: str, payload) -> bool:
        """The live source asks: is this payload (on ``<prefix>/<scanner>/<leaf>``) this member's?

        ``payload`` is the ZBytes; it is read only for ScanStart / ScanEnd.  What is not
        admitted is counted as "other member".  Anything malformed is admitted: the
        ingest rejects it, with its reason.
        """
        try:
            validate_identifier(scanner)
        except InvalidIdentifierError:
            return True
        with self._lock:
            if leaf == "scan":
                mine = self._follow(scanner, encoding, payload)
            else:
                mine = self.owner_of(scanner) == self.me
            if not mine:
                self.stats[f"dropped: {OTHER_MEMBER}"] += 1
            return mine

    def _follow(self, scanner: str, encoding: str, payload) -> bool:
        data = payload.to_bytes() if hasattr(payload, "to_bytes") else bytes(payload)
        type_name = encoding.partition(";")[2]
        cls = codec.MESSAGE_TYPES.get(type_name)
        if cls not in (codec.ScanStart, codec.ScanEnd):
            return True
        try:
            msg = cls.FromString(data)
        except Exception:  # noqa: BLE001 - malformed: let the ingest reject and count it
            return True
        if msg.scanner_id != scanner:
            return True  # the ingest rejects the mismatch
        scans = self._scans.get(scanner)
        if scans is None:
            scans = self._scans[scanner] = OrderedDict()
            while len(self._scans) > self.config.max_scanners:
                self._scans.popitem(last=False)
                self.stats["evicted: scanner forgotten (max_scanners)"] += 1
        self._scans.move_to_end(scanner)
        scans.pop(None, None)  # the guess made before any ScanStart was seen
        if isinstance(msg, codec.ScanStart):
            start_ns = int(msg.start_time_ns)
            rec = scans.get(msg.scan_id)
            if rec is None:
                who = owner(scanner, eligible(self.members, start_ns, self.me, self._settle_ns))
                rec = scans[msg.scan_id] = _Scan(who, start_ns, returns=self._returns)
            rec.start = (encoding, data)
        else:
            rec = scans.get(msg.scan_id)
            if rec is None:
                who = owner(scanner, eligible(self.members, None, self.me, self._settle_ns))
                rec = scans[msg.scan_id] = _Scan(who, returns=self._returns)
            rec.end = (encoding, data)
        scans.move_to_end(msg.scan_id)
        while len(scans) > self.config.keep_scans:
            scans.popitem(last=False)
            self.stats["evicted: scan forgotten (keep_scans)"] += 1
        return rec.owner == self.me

    # --- finals ---
    def may_publish(self, message: codec.Reconstruction) -> bool:
        """The fence: whether this member should publish ``message`` (see the module's notes).

        Not of a scan another member owns now; and, for a final of a scan during which a member
        came back from a partition, not if another member's table says it published that final.
        """
        key = (message.scanner_id, message.scan_id)
        with self._lock:
            scans = self._scans.get(key[0])
            rec = scans.get(key[1]) if scans is not None else None
            if rec is None:
                return True
            if rec.owner != self.me:
                self.stats["fenced: estimate of a scan another member owns"] += 1
                return False
            if wire.is_terminal(message) and rec.done and key not in self._published:
                self.stats["fenced: final another member already published"] += 1  # its done mark came
                return False
            # Another member can have published this final only if it took the scan over while this one
            # was cut off, i.e. if a member came back since the scan began.  A death alone asks nothing
            # (the question would wait on the dead member's queryable until its lease ran out).
            disturbed = rec.returns != self._returns
        if wire.is_terminal(message) and disturbed and self._published_elsewhere(*key):
            self.stats["fenced: final another member already published"] += 1
            _log.warning(
                "group %s: fenced: the final of (%s, %d) was already published by another member "
                "(a partition made each side take the other's scans)",
                self.config.group,
                *key,
            )
            with self._lock:
                rec.done = True
            return False
        return True

    def fenced(self, publish: Callable[[codec.Reconstruction], None]) -> Callable[[codec.Reconstruction], None]:
        """``publish`` behind the fence: how a member publishes (``reconstruct --group``, bench fleet, the tests).

        The returned function publishes a message only if :meth:`may_publish` allows it, and then
        marks a final done for the group (:meth:`on_estimate`): the mark never precedes the final,
        and a fenced estimate is neither published nor marked.
        """

        def publish_fenced(message: codec.Reconstruction) -> None:
            if self.may_publish(message):
                publish(message)
                self.on_estimate(message)

        return publish_fenced

    def on_estimate(self, message: codec.Reconstruction) -> None:
        """Call after publishing an estimate: a terminal one is marked done for the group."""
        if wire.is_terminal(message):
            with self._lock:
                self._published[(message.scanner_id, message.scan_id)] = None
                while len(self._published) > self.config.keep_finals:
                    self._published.popitem(last=False)
            self._done_pub.put(f"{message.scanner_id}/{message.scan_id}".encode())

    def _published_elsewhere(self, scanner: str, scan_id: int) -> bool:
        """Ask every other member's table whether it published this final (waits ≤ join_timeout)."""
        try:
            replies = self._session.get(
                f"{finals_key(self.prefix, self.config.group)}?scanner={scanner};scan={scan_id}",
                timeout=self.config.join_timeout,
            )
            for reply in replies:
                ok = reply.ok
                if ok is not None and not str(ok.key_expr).endswith(f"/{self.me}") and ok.payload.to_bytes() == b"done":
                    return True
        except zenoh.ZError as exc:
            self.stats["errors: finals query"] += 1
            _log.warning(
                "group %s: could not ask the others' finals of (%s, %d): %s; publishing",
                self.config.group,
                scanner,
                scan_id,
                exc,
            )
        return False

    def _answer_finals(self, query: zenoh.Query) -> None:
        try:
            params = query.parameters
            key = (validate_identifier(params.get("scanner") or ""), int(params.get("scan") or ""))
        except (InvalidIdentifierError, ValueError, TypeError):
            self.stats["rejected: malformed finals query"] += 1
            return  # dropping the query ends it with no reply
        try:
            with self._lock:
                done = key in self._published
            if done:
                query.reply(self._finals_key, b"done")
        except zenoh.ZError:  # the querier is gone
            self.stats["errors: finals reply"] += 1

    def _on_done(self, sample: zenoh.Sample) -> None:
        try:
            scanner, _, scan_id = sample.payload.to_bytes().decode("ascii").partition("/")
            sid = int(scan_id)
        except (UnicodeDecodeError, ValueError):
            self.stats["rejected: malformed done mark"] += 1
            return
        with self._lock:
            scans = self._scans.get(scanner)
            rec = scans.get(sid) if scans is not None else None
            if rec is not None:
                rec.done = True

    # --- membership ---
    def _on_token(self, sample: zenoh.Sample) -> None:
        try:
            adopted = self._apply_token(sample)
            # Fed after the lock is released: the live source's FIFO can be full, and the worker that drains
            # it asks may_publish / admit (this lock) first; feeding it under the lock deadlocked the two.
            for enqueue, encoding, data, scanner in adopted:
                enqueue(encoding, data, "live", scanner)
        except Exception:  # noqa: BLE001 - never into Zenoh's thread; a lost change is logged and counted
            self.stats["errors: membership callback"] += 1
            _log.exception("group %s: a membership change could not be applied", self.config.group)

    def _apply_token(self, sample: zenoh.Sample) -> list[tuple[Callable, str, bytes, str]]:
        """Apply a member's token (put: joined, delete: left); returns the adopted scans' kept messages to feed."""
        parts = str(sample.key_expr).rsplit("/", 2)
        try:
            member, joined = validate_identifier(parts[1], what="member id"), int(parts[2])
        except (IndexError, ValueError, InvalidIdentifierError):
            self.stats["rejected: malformed member token"] += 1
            return []
        adopted: list[tuple[Callable, str, bytes, str]] = []
        with self.changed:
            if sample.kind == zenoh.SampleKind.PUT:
                if member == self.me:
                    if joined != self.joined_ns:  # two processes with one id would both process its share
                        self.stats["conflict: member id used by another process"] += 1
                        _log.error(
                            "group %s: another process joined as member %s; give each member a unique "
                            "--member-id (or leave it to the default)",
                            self.config.group,
                            member,
                        )
                    return adopted
                if self.members.get(member) == joined:
                    return adopted  # seen twice: by the subscriber's history and by the join query
                if member not in self.members and len(self.members) >= self.config.max_members:
                    self.stats["refused: member over max_members"] += 1
                    _log.warning(
                        "group %s: ignoring member %s (more than %d members)",
                        self.config.group,
                        member,
                        self.config.max_members,
                    )
                    return adopted
                self.members[member] = max(joined, self.members.get(member, joined))
                self.stats["members joined"] += 1
                _log.info("group %s: member %s joined (%d members)", self.config.group, member, len(self.members))
                if self._departed.pop(member, None) == joined:
                    self._returns += 1
                    self._hand_back(member)
            elif member != self.me and self.members.get(member) == joined:
                del self.members[member]
                self._departed[member] = joined
                while len(self._departed) > self.config.max_members:
                    self._departed.popitem(last=False)
                self.stats["members left"] += 1
                _log.info("group %s: member %s left (%d members)", self.config.group, member, len(self.members))
                adopted = self._reassign(member)
            self.changed.notify_all()
        return adopted

    def _hand_back(self, member: str) -> None:
        """A member given up for gone is back (a healed partition): its unfinished scans return to it."""
        for scans in self._scans.values():
            for rec in scans.values():
                if rec.taken_from == member and not rec.done:
                    if rec.owner == self.me:
                        self.stats["scans handed back"] += 1
                    rec.owner, rec.taken_from = member, None

    def _reassign(self, gone: str) -> list[tuple[Callable, str, bytes, str]]:
        """The scans of a member that left, without a final, go to the members left; adopt ours.

        Returns (enqueue, encoding, payload, scanner) of the kept ScanStart / ScanEnd of the scans
        adopted, for the caller to feed once it has released the lock.
        """
        adopted = []
        for scanner, scans in self._scans.items():
            for scan_id, rec in scans.items():
                if rec.owner != gone:
                    continue
                if scan_id is None:  # a guess, no scan seen: decided afresh at the next payload
                    rec.owner = owner(scanner, eligible(self.members, None, self.me, self._settle_ns))
                    continue
                rec.owner = owner(
                    scanner,
                    eligible(self.members, rec.start_ns, self.me, self._settle_ns)
                    if rec.start_ns is not None
                    else list(self.members),
                )
                rec.taken_from = gone
                if rec.owner != self.me or rec.done:
                    continue
                self.stats["scans adopted"] += 1
                _log.info("group %s: adopting scan (%s, %d) of member %s", self.config.group, scanner, scan_id, gone)
                if self._enqueue is None:
                    self.stats["adoption without a live source (recovered at its next payload)"] += 1
                    continue
                adopted += [(self._enqueue, *kept, scanner) for kept in (rec.start, rec.end) if kept is not None]
        return adopted

    def stats_dict(self) -> dict:
        with self._lock:
            return {"group": self.config.group, "member": self.me, "members": sorted(self.members), **dict(self.stats)}
