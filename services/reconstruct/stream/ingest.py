"""The one way in for live and recorded data: decode, validate, route to its scan.

A payload arrives with its type name (the Zenoh encoding's schema, or the MCAP
schema name).  It is decoded and validated by :func:`lelsonar.codec.decode`,
then routed to the :class:`ScanAssembly` of its (scanner, scan).  Each payload is
parsed once.  A ``Sample`` for a scan already open is routed on its header alone
and its body checked in the pass that places it, the same checks with the same
refusals: read straight from its payload where it has the scan's layout
(:mod:`~lelsonar.reconstruct.stream.fastwire`, :meth:`ScanAssembly.add_payload`),
else parsed (:meth:`ScanAssembly.add` with ``limits``).  Whatever is
wrong is counted by error type and reported — never raised to the caller — so a
service keeps serving.  Samples that arrive before their ``ScanStart`` wait in
a bounded buffer.

Every table here is keyed by wire data and bounded; what a bound pushes out is
counted in :attr:`Ingest.evicted` by reason.  A message carries its origin:
"live" (the stream) or "recovered" (the acquirer's log), for the accounting.
"""

from __future__ import annotations

import functools
import logging
from collections import Counter, OrderedDict
from dataclasses import dataclass, field
from typing import NamedTuple

from lelsonar import SCHEMA_VERSION, codec
from lelsonar.errors import (
    DecodeError,
    InvalidMessageError,
    LelsonarError,
    ScannerMismatchError,
)
from lelsonar.reconstruct.stream.assembly import ScanAssembly
from lelsonar.reconstruct.stream.fastwire import sample_header

_log = logging.getLogger(__name__)

ScanKey = tuple[str, int]


@dataclass(frozen=True)
class Rejected:
    """A payload that could not be used, and why."""

    error: str  # the error class, e.g. "TruncatedDataError", "UnknownScan"
    detail: str


class Accepted(NamedTuple):
    """A message that changed a scan: its kind is "start", "sample" or "end".  (A named tuple: one is made
    a sample, and it costs half a frozen dataclass.)"""

    kind: str
    scan: ScanAssembly
    step: int | None = None


#: Accepted((kind, scan, step)) without the named tuple's Python-level __new__ (a third of its cost).
_accepted = functools.partial(tuple.__new__, Accepted)
_MESSAGE_TYPES, _SAMPLE, _SCAN_START = codec.MESSAGE_TYPES, codec.Sample, codec.ScanStart


@dataclass
class Ingest:
    """Routes validated messages to scans, keyed by (scanner, scan).

    Parameters
    ----------
    limits : DecodeLimits
    max_scans : int
        Scans kept at once; the oldest are forgotten first.
    max_pending : int
        Messages (samples, and a ScanEnd) held, over all scans, while their ScanStart has not arrived.
    """

    limits: codec.DecodeLimits = codec.DEFAULT_LIMITS
    max_scans: int = 256
    max_pending: int = 4096
    max_closed: int = 4096
    scans: OrderedDict[ScanKey, ScanAssembly] = field(default_factory=OrderedDict)
    closed: OrderedDict[ScanKey, None] = field(default_factory=OrderedDict)
    #: Messages waiting for their ScanStart, with their origin: samples, and possibly the ScanEnd.
    pending: OrderedDict[ScanKey, list[tuple[codec.Sample | codec.ScanEnd, str]]] = field(default_factory=OrderedDict)
    rejected: Counter[str] = field(default_factory=Counter)
    #: What a bound pushed out, by reason (nothing leaves a table uncounted).
    evicted: Counter[str] = field(default_factory=Counter)
    accepted: int = 0
    #: Steps whose carried ``Sample.sensor_energy`` disagreed with their waveforms, over every scan so far, open
    #: or closed (each scan counts its own in ``ScanAssembly.energy_mismatches``); recomputed, not rejected.
    energy_mismatches: int = 0
    #: Recovery replies for scans already finalised (not rejected input: nothing was lost).
    recovered_after_close: int = 0
    #: Keys that started waiting for their ScanStart since the caller last emptied this list.
    newly_pending: list[ScanKey] = field(default_factory=list)
    #: Finalised scans a message came for since the caller last emptied this list (it may re-finalise them).
    late: list[ScanKey] = field(default_factory=list)
    #: Read a Sample of an open scan straight from its payload (:mod:`~lelsonar.reconstruct.stream.fastwire`)
    #: where it has the scan's layout; False parses every payload (the baseline `lelsonar bench ingest` shows).
    fast_path: bool = True
    _held: int = 0
    #: By the key a sample came on (None: no key), the bytes that routed the last one read from its payload, their
    #: length, its scan and (0, 0) for the step and time read after them (:meth:`_route`; open: forgotten as it
    #: closes; at most two entries an open scan, its scanner's key and none).
    _routes: dict[str | None, tuple[bytes, int, ScanAssembly, int, int]] = field(default_factory=dict)
    #: By scanner, the layout its last scan's samples showed (:attr:`ScanAssembly.layout`), for its next scan's first
    #: sample (:meth:`ScanAssembly.expect_layout`); at most ``max_scans`` scanners, the least recent forgotten first.
    _layouts: OrderedDict[str, list] = field(default_factory=OrderedDict)
    #: By scanner, the last ScanStart it sent that passed every check, the limits they were made under
    #: (:meth:`_decode_start`) and its scans' :class:`~lelsonar.reconstruct.stream.scan_arrays.ScanDescription` once
    #: one was made; at most ``max_scans`` scanners, the least recent forgotten first.
    _starts: OrderedDict[str, list] = field(default_factory=OrderedDict)
    #: The ScanStart :meth:`_decode_start` passed last and its scanner's entry of ``_starts`` (whose ScanStart equals
    #: it but for ``scan_id`` and ``start_time_ns``), for :meth:`_start` to make its scan from that description.
    _passed: tuple[codec.ScanStart, list] | None = None

    @property
    def n_pending(self) -> int:
        return self._held

    def accept(
        self, type_name: str, payload: bytes, *, origin: str = "live", key_scanner: str | None = None
    ) -> list[Accepted | Rejected]:
        """Decode one payload and apply it; return what changed (or why nothing did).

        ``key_scanner``: the scanner id in the key the payload came on (live data);
        a payload that claims another scanner is rejected as ``ScannerMismatchError``.
        """
        message: codec.WireMessage
        try:
            cls = _MESSAGE_TYPES.get(type_name)
            if cls is _SAMPLE:
                limits = self.limits
                small = len(payload) <= limits.max_payload_bytes
                if small and type(payload) is not bytes:
                    payload = bytes(payload)  # (a zenoh.ZBytes) copied once: the fast path or the parser reads it
                if small and self.fast_path:
                    # Placed in its open scan straight from its bytes, never parsed (ScanAssembly.add_payload), where
                    # it is routed (:meth:`_route`); else left to the parser.  (Inline: every sample runs it.)
                    route = self._routes.get(key_scanner)
                    if route is None or not payload.startswith(route[0]):
                        route = self._route(payload, key_scanner)
                    if route is not None:
                        _, at, scan, step, time_ns = route
                        mismatches = scan.energy_mismatches
                        try:
                            placed = scan.add_payload(payload, at, step, time_ns, origin, limits)
                        except DecodeError as exc:
                            header = sample_header(payload)
                            return [self._refused(scan, -1 if header is None else header[3], exc)]
                        if placed >= 0:
                            if scan.energy_mismatches != mismatches:
                                self.energy_mismatches += scan.energy_mismatches - mismatches
                            self.accepted += 1
                            return [_accepted(("sample", scan, placed))]
                message = codec.parse(payload, cls, limits)
                opened = self.scans.get((message.scanner_id, message.scan_id))  # (an open scan is never a closed one)
                if opened is not None and (key_scanner is None or message.scanner_id == key_scanner):
                    # Straight to its scan, which checks the body in the pass that places it (or has it checked
                    # here first, as decoding does, if that does not clear it).
                    return [self._add(opened, message, origin, self.limits)]
                codec.validate_body(message, self.limits)
            elif cls is None or cls is codec.Reconstruction:
                raise InvalidMessageError(f"unexpected payload type {type_name[:80]!r}")
            elif cls is _SCAN_START:
                message = self._decode_start(payload)
            else:
                message = codec.decode(payload, cls, self.limits)
            if key_scanner is not None and message.scanner_id != key_scanner:
                raise ScannerMismatchError(
                    f"{cls.DESCRIPTOR.name} claims scanner {message.scanner_id!r} but came on the key of scanner "
                    f"{key_scanner[:80]!r}; dropped (a forgery, or a publisher misconfigured with the wrong "
                    "--scanner-id)"
                )
            return self.apply(message, origin=origin)
        except LelsonarError as exc:
            return [self._reject(type(exc).__name__, str(exc))]

    def apply(self, message, *, origin: str = "live") -> list[Accepted | Rejected]:
        """Apply an already validated message (``origin``: "live" or "recovered")."""
        key = (message.scanner_id, message.scan_id)
        if key in self.closed:
            if len(self.late) < self.max_pending and (not self.late or self.late[-1] != key):  # bounded
                self.late.append(key)
            if origin == "recovered":
                # A recovery reply that came after the verdict (asked twice, or the live copy won):
                # nothing was lost, so it is counted apart from rejected input.
                self.recovered_after_close += 1
                return []
            return [self._reject("LateMessage", f"{type(message).__name__} for scan {key}, already finalised")]
        if isinstance(message, codec.ScanStart):
            return self._start(key, message)
        scan = self.scans.get(key)
        if isinstance(message, codec.Sample):
            if scan is None:
                return self._hold(key, message, origin)
            return [self._add(scan, message, origin)]
        if scan is None:  # a ScanEnd before its ScanStart: held like a sample (a late start may recover it)
            return self._hold(key, message, origin)
        if scan.end is not None:
            scan.rejected["DuplicateScanEnd"] += 1
            return [self._reject("DuplicateScanEnd", f"second ScanEnd for scan {key} ignored")]
        if message.samples_sent > scan.start.steps:
            scan.rejected["InvalidMessageError"] += 1
            return [
                self._reject(
                    "InvalidMessageError",
                    f"ScanEnd of scan {key} counts {message.samples_sent} "
                    f"samples; its ScanStart planned {scan.start.steps}",
                )
            ]
        scan.end = message
        self.accepted += 1
        return [Accepted("end", scan)]

    def close(self, key: ScanKey) -> None:
        """The scan is finalised: drop its data; later messages for it are rejected as late."""
        self._forget_routes(self.scans.pop(key, None))
        self._held -= len(self.pending.pop(key, []))
        self.closed[key] = None
        while len(self.closed) > self.max_closed:
            self.closed.popitem(last=False)
            self.evicted["closed scan forgotten (max_closed)"] += 1

    def drop_pending(self, key: ScanKey) -> list[Rejected]:
        """Give up on samples whose ScanStart never came (called on timeout)."""
        held = self.pending.pop(key, [])
        self._held -= len(held)
        return (
            [self._reject("UnknownScan", f"{len(held)} messages of scan {key} never got a ScanStart")] if held else []
        )

    # --- internals -------------------------------------------------------------------
    def _start(self, key: ScanKey, start: codec.ScanStart) -> list[Accepted | Rejected]:
        passed, self._passed = self._passed, None
        if key in self.scans:
            return [self._reject("DuplicateScanStart", f"second ScanStart for scan {key} ignored")]
        entry = passed[1] if passed is not None and passed[0] is start else None
        try:
            scan = ScanAssembly(start, described=None if entry is None else entry[2])
        except LelsonarError as exc:
            return [self._reject(type(exc).__name__, f"ScanStart {key}: {exc}")]
        if entry is not None:
            entry[2] = scan.description
        self.scans[key] = scan
        scan.expect_layout(self._layouts.get(key[0]))
        while len(self.scans) > self.max_scans:
            old, dropped = self.scans.popitem(last=False)
            self._forget_routes(dropped)
            self.evicted["open scan forgotten (max_scans)"] += 1
            _log.warning(
                "forgetting scan %s with %d samples: more than %d scans open (counted in evicted)",
                old,
                dropped.n_received,
                self.max_scans,
            )
        self.accepted += 1
        events: list[Accepted | Rejected] = [Accepted("start", scan)]
        waiting = self.pending.pop(key, [])
        self._held -= len(waiting)
        for held, origin in waiting:
            if isinstance(held, codec.Sample):
                events.append(self._add(scan, held, origin))
            else:  # the ScanEnd, now that its scan is known
                events += self.apply(held, origin=origin)
        return events

    def _decode_start(self, payload: bytes) -> codec.ScanStart:
        """:func:`lelsonar.codec.decode` of a ``ScanStart``, the same checks and refusals: its header checked as it is
        parsed (:func:`~lelsonar.codec.parse`), its body (:func:`~lelsonar.codec.validate_body`) unless it equals, but
        for ``scan_id`` and ``start_time_ns`` (which no check reads), its scanner's last ScanStart that passed them
        under the same limits: each check reads the message's fields alone, so equal fields pass as those did (a
        scanner sends the same description scan after scan, and comparing two messages is one call into upb).

        Raises
        ------
        DecodeError
            A subclass that says what was wrong, as :func:`~lelsonar.codec.decode`.
        """
        limits = self.limits
        message = codec.parse(payload, _SCAN_START, limits)
        starts = self._starts
        known = starts.get(message.scanner_id)
        if known is not None and known[0] is limits:
            passed = known[1]
            passed.scan_id, passed.start_time_ns = message.scan_id, message.start_time_ns
            if passed == message:
                self._passed = (message, known)
                return message
        codec.validate_body(message, limits)
        passed = _SCAN_START()
        passed.CopyFrom(message)  # (a copy of its own: the message goes to its scan)
        known = starts[message.scanner_id] = [limits, passed, None]
        self._passed = (message, known)
        starts.move_to_end(message.scanner_id)
        while len(starts) > self.max_scans:
            starts.popitem(last=False)
            self.evicted["scanner start forgotten (max_scans)"] += 1
        return message

    def _route(self, payload: bytes, key_scanner: str | None) -> tuple[bytes, int, ScanAssembly, int, int] | None:
        """Where a ``Sample``'s payload goes on the fast path: ``(prefix, at, scan, step, time_ns)``, its open scan and
        its header read up to ``at`` (:meth:`ScanAssembly.add_payload`'s arguments); None where the fast path leaves
        it to the parser.  If the fields that route it (``schema_version``, ``scanner_id``, ``scan_id``) come first,
        each once, the bytes they span route the next payloads of its key that start with them (the same fields,
        which the rest may not repeat) to the same scan, their headers not read in Python."""
        header = sample_header(payload)
        if header is None or header[0] != SCHEMA_VERSION:
            return None
        _, scanner, scan_id, step, time_ns, routed, at = header
        scan = self.scans.get((scanner, scan_id))  # (an open scan: its scanner id was validated with its start)
        if scan is None or (key_scanner is not None and scanner != key_scanner):
            return None
        if routed:
            self._routes[key_scanner] = (payload[:routed], routed, scan, 0, 0)
        return b"", at, scan, step, time_ns

    def _add(
        self,
        scan: ScanAssembly,
        sample: codec.Sample,
        origin: str = "live",
        limits: codec.DecodeLimits | None = None,
    ) -> Accepted | Rejected:
        """Place a sample in its scan; ``limits``: its body is not validated yet (:func:`~lelsonar.codec.parse`
        only), and a refusal of the decoding is raised (for :meth:`accept` to count), never the scan's."""
        mismatches = scan.energy_mismatches
        try:
            placed = scan.add(sample, origin, limits=limits)
        except DecodeError as exc:
            return self._refused(scan, sample.step, exc)
        if placed is None:  # not cleared by the scan's pass: validated as decoding does, then placed
            # A refusal of the decoding: raised, for accept to count (``limits`` is set: only then is None returned).
            codec.validate_body(sample, self.limits if limits is None else limits)
            try:
                placed = scan.add(sample, origin)
            except DecodeError as exc:
                return self._refused(scan, sample.step, exc)
        if not placed:
            return self._reject("DuplicateSample", f"step {sample.step} of scan {scan.key} arrived twice")
        self._note_layout(scan)
        # Counted here, as they happen (the stats read one number, never the open scans a worker changes).
        self.energy_mismatches += scan.energy_mismatches - mismatches
        self.accepted += 1
        return _accepted(("sample", scan, sample.step))

    def _refused(self, scan: ScanAssembly, step: int, exc: DecodeError) -> Rejected:
        """The scan's own refusal of a (valid) sample of step ``step``, counted by the scan too."""
        scan.rejected[type(exc).__name__] += 1
        return self._reject(type(exc).__name__, f"scan {scan.key} step {step}: {exc}")

    def _hold(
        self, key: ScanKey, message: codec.Sample | codec.ScanEnd, origin: str = "live"
    ) -> list[Accepted | Rejected]:
        if key not in self.pending:
            _log.info("holding messages of scan %s until its ScanStart arrives", key)
            if len(self.newly_pending) < self.max_pending:  # bounded even if no one empties it
                self.newly_pending.append(key)
        held = self.pending.setdefault(key, [])
        if isinstance(message, codec.ScanEnd) and any(isinstance(m, codec.ScanEnd) for m, _ in held):
            return [self._reject("DuplicateScanEnd", f"second ScanEnd for scan {key} ignored")]
        held.append((message, origin))
        self._held += 1
        out: list[Accepted | Rejected] = []
        while self.n_pending > self.max_pending:
            old = next(iter(self.pending))
            out += self.drop_pending(old)
        return out

    def _note_layout(self, scan: ScanAssembly) -> None:
        """Keep the layout a parsed sample showed ``scan`` for its scanner's next scan (bounded, evictions counted)."""
        layout = scan.layout
        if layout is None:
            return
        scanner = scan.start.scanner_id
        layouts = self._layouts
        if layouts.get(scanner) is not layout:
            layouts[scanner] = layout
            layouts.move_to_end(scanner)
            while len(layouts) > self.max_scans:
                layouts.popitem(last=False)
                self.evicted["scanner layout forgotten (max_scans)"] += 1

    def _forget_routes(self, scan: ScanAssembly | None) -> None:
        """No payload is routed to ``scan`` (closed, or forgotten) by the bytes that routed it."""
        if scan is not None:
            for key in [key for key, route in self._routes.items() if route[2] is scan]:
                del self._routes[key]

    def _reject(self, error: str, detail: str) -> Rejected:
        self.rejected[error] += 1
        _log.warning("rejected input (%s, %d so far): %s", error, self.rejected[error], detail)
        return Rejected(error, detail)
