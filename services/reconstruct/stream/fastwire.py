"""A ``Sample`` read straight from its payload, without the protobuf parser: the ingest's fast path.

The acquisition service's samples all have one layout (the capsules in the ScanStart's order, float32
waveforms of one length on one clock).  For a scan whose layout is known, a sample's header
(:func:`read_header`) and body (:func:`read_body`) are read from the protobuf wire format in compiled code,
bit for bit what the parser gives, and the payload is parsed once.  The two walk the top level in turn: the
header is the fields before the first other one, the body the rest, so that routing a sample touches only
its first cache line.  The waveforms are read where they lie in the payload, never copied.  Only a payload
plainly encoded (each field once, with its own wire type, no groups,
canonical field numbers, the header first) on that layout is read; anything else,
however valid, is left to :func:`lelsonar.codec.parse` (the readers say so, nothing else).  A differential
test holds the readers to ``protobuf`` on valid messages of every shape and on mutated bytes.

The field numbers read are literals, so that the compiled code (cached by this file's contents) never holds
numbers other than these, and are checked against the generated descriptors on import.
"""

from __future__ import annotations

import numpy as np

from lelsonar import codec
from lelsonar.errors import ConfigError, InternalError
from lelsonar.reconstruct.stream.step_features import PER_CAPSULE, PER_STEP, STREAM_AHEAD, place_rows, prefetch_rows
from lelsonar.signal.compiled import array_at, float32_at, kernel, prefetch, unowned
from lelsonar.v1 import scan_pb2

_FLOAT32 = scan_pb2.WAVEFORM_ENCODING_FLOAT32_LE
_SAMPLE_VERSION, _SAMPLE_SCANNER, _SAMPLE_SCAN, _SAMPLE_STEP, _SAMPLE_TIME = 1, 2, 3, 4, 5
# generated descriptors on import.
_SAMPLE_GAMMA_COMMANDED, _SAMPLE_GAMMA_MEASURED, _SAMPLE_MOTOR, _SAMPLE_SENSORS, _SAMPLE_ENERGY = 6, 7, 8, 9, 10
_MOTOR_LOAD, _MOTOR_VOLTAGE, _MOTOR_TEMPERATURE = 2, 3, 4
_READING_CAPSULE, _READING_VALID, _READING_TOF, _READING_DISTANCE, _READING_WAVEFORM = 1, 2, 3, 4, 5
_WAVE_ENCODING, _WAVE_DATA, _WAVE_RATE, _WAVE_T0, _WAVE_COUNT = 1, 2, 4, 5, 6
for _message, _fields in (
    (
        codec.Sample,
        {
            "schema_version": _SAMPLE_VERSION,
            "scanner_id": _SAMPLE_SCANNER,
            "scan_id": _SAMPLE_SCAN,
            "step": _SAMPLE_STEP,
            "acquisition_time_ns": _SAMPLE_TIME,
            "gamma_commanded": _SAMPLE_GAMMA_COMMANDED,
            "gamma_measured": _SAMPLE_GAMMA_MEASURED,
            "motor": _SAMPLE_MOTOR,
            "sensors": _SAMPLE_SENSORS,
            "sensor_energy": _SAMPLE_ENERGY,
        },
    ),
    (scan_pb2.MotorStatus, {"load": _MOTOR_LOAD, "voltage": _MOTOR_VOLTAGE, "temperature": _MOTOR_TEMPERATURE}),
    (
        scan_pb2.SensorReading,
        {
            "capsule_id": _READING_CAPSULE,
            "echo_valid": _READING_VALID,
            "time_of_flight": _READING_TOF,
            "distance": _READING_DISTANCE,
            "waveform": _READING_WAVEFORM,
        },
    ),
    (
        codec.Waveform,
        {
            "encoding": _WAVE_ENCODING,
            "data": _WAVE_DATA,
            "sample_rate": _WAVE_RATE,
            "t0": _WAVE_T0,
            "sample_count": _WAVE_COUNT,
        },
    ),
):
    if {name: _message.DESCRIPTOR.fields_by_name[name].number for name in _fields} != _fields:
        raise ConfigError(
            f"lelsonar.v1.{_message.DESCRIPTOR.name}'s field numbers are not the ones "
            "fastwire reads: a schema that breaks the wire format"
        )
del _message, _fields
_VARINT, _FIXED64, _LENGTH, _FIXED32 = 0, 1, 2, 5
#: :func:`place_wire`'s: a payload not read (not plainly encoded, or not the fast path's layout), nothing written;
#: the scan's arrays to grow to its step first, nothing written.
UNREAD, GROW = -3, -4
_ONE = 0x3FF0000000000000  # 1.0's bits


@kernel
def _wire_varint(buf, i, end):
    """The base-128 varint at ``buf[i:end]``, and the index after it (-1: none there)."""
    value = np.uint64(0)
    shift = np.uint64(0)
    while i < end and shift < 64:
        b = np.uint64(buf[i])
        i += 1
        value |= (b & np.uint64(0x7F)) << shift
        if b < 0x80:
            return value, i
        shift += np.uint64(7)
    return value, -1


@kernel
def _wire_tag(buf, i, end):
    """The field number and wire type of the tag at ``buf[i:end]``, and the index after it (-1: none there, or
    not a tag the parser accepts: field number 0, or beyond 2^29 − 1)."""
    tag, i = _wire_varint(buf, i, end)
    field = np.int64(tag >> np.uint64(3))
    if i < 0 or field == 0 or field >= (1 << 29):
        return 0, 0, -1
    return field, np.int64(tag & np.uint64(7)), i


@kernel
def _wire_fixed64(buf, i):
    """The little-endian 64 bits at ``buf[i:i + 8]`` (a double's, bit for bit)."""
    value = np.uint64(0)
    for j in range(8):
        value |= np.uint64(buf[i + j]) << np.uint64(8 * j)
    return value


@kernel
def _wire_length(buf, i, end):
    """The bounds (start, end) of the length-delimited field whose length is at ``buf[i:end]``; (-1, -1): none."""
    size, i = _wire_varint(buf, i, end)
    if i < 0 or size > end - i:
        return -1, -1
    return i, i + np.int64(size)


@kernel
def _wire_skip(buf, i, end, wire_type):
    """The index after a field of ``wire_type`` whose value starts at ``buf[i]`` (-1: a group, or malformed)."""
    if wire_type == _VARINT:
        return _wire_varint(buf, i, end)[1]
    if wire_type == _FIXED64:
        return i + 8 if i + 8 <= end else -1
    if wire_type == _LENGTH:
        return _wire_length(buf, i, end)[1]
    if wire_type == _FIXED32:
        return i + 4 if i + 4 <= end else -1
    return -1


@kernel
def _read_reading(buf, i, end, capsule_id, bits, at, clock, n):
    """One ``SensorReading`` (``buf[i:end]``) of :func:`read_body`: its ``echo_valid, distance,
    time_of_flight`` into ``bits[at:at + 3]`` (1.0 or 0.0, and the doubles' bits), and where its waveform's
    samples start in ``buf``; -1 (``bits`` then partly written) unless the reading is plainly encoded and on the
    fast path's layout: ``capsule_id``, a float32 waveform of ``n`` samples on the clock whose bits are
    ``bits[clock:clock + 2]`` (rate, t0)."""
    bits[at] = 0
    bits[at + 1] = 0
    bits[at + 2] = 0
    valid = capsule = np.uint64(0)
    seen = 0
    a = b = -1
    while i < end:
        field, wire_type, i = _wire_tag(buf, i, end)
        if i < 0:
            return -1
        if field == _READING_CAPSULE or field == _READING_VALID:
            if wire_type != _VARINT or seen & (1 << field):
                return -1
            v, i = _wire_varint(buf, i, end)
            if i < 0:
                return -1
            if field == _READING_CAPSULE:
                capsule = v
            else:
                valid = v
        elif field == _READING_TOF or field == _READING_DISTANCE:
            if wire_type != _FIXED64 or seen & (1 << field) or i + 8 > end:
                return -1
            bits[at + 2 if field == _READING_TOF else at + 1] = _wire_fixed64(buf, i)
            i += 8
        elif field == _READING_WAVEFORM:
            if wire_type != _LENGTH or seen & (1 << field):
                return -1
            a, b = _wire_length(buf, i, end)
            if a < 0:
                return -1
            i = b
        else:  # a field this build does not know: skipped, as the parser keeps it aside
            i = _wire_skip(buf, i, end, wire_type)
            if i < 0:
                return -1
            continue
        seen |= 1 << field
    if capsule != capsule_id or a < 0:
        return -1
    if valid != 0:  # (a bool is any varint but 0)
        bits[at] = _ONE
    encoding = count = rate = t0 = np.uint64(0)
    d0 = d1 = -1
    seen = 0
    i = a
    while i < b:
        field, wire_type, i = _wire_tag(buf, i, b)
        if i < 0:
            return -1
        if field == _WAVE_ENCODING or field == _WAVE_COUNT:
            if wire_type != _VARINT or seen & (1 << field):
                return -1
            v, i = _wire_varint(buf, i, b)
            if i < 0:
                return -1
            if field == _WAVE_ENCODING:
                encoding = v
            else:
                count = v
        elif field == _WAVE_RATE or field == _WAVE_T0:
            if wire_type != _FIXED64 or seen & (1 << field) or i + 8 > b:
                return -1
            if field == _WAVE_RATE:
                rate = _wire_fixed64(buf, i)
            else:
                t0 = _wire_fixed64(buf, i)
            i += 8
        elif field == _WAVE_DATA:
            if wire_type != _LENGTH or seen & (1 << field):
                return -1
            d0, d1 = _wire_length(buf, i, b)
            if d0 < 0 or d1 - d0 != 4 * n:
                return -1
            i = d1
        else:
            i = _wire_skip(buf, i, b, wire_type)
            if i < 0:
                return -1
            continue
        seen |= 1 << field
    # The layout's clock to the bit (stricter than ==, which the fast path's clocks, finite, need no more of).
    if (d0 >= 0 or n == 0) and encoding == _FLOAT32 and count == n and rate == bits[clock] and t0 == bits[clock + 1]:
        return max(d0, 0)
    return -1


@kernel
def read_sample(payload, body, ids, values, waveforms):
    """:func:`read_body` of a ``Sample``'s ``payload``, its waveforms' samples copied into ``waveforms``
    ((k, n) float32): bit for bit what the parsed message's fields hold.

    Returns
    -------
    int
        How many energies the sample carries (≥ 0), or -1: not read (``values`` and ``waveforms`` then partly
        written).
    """
    buf = np.frombuffer(payload, dtype=np.uint8)
    k, n = waveforms.shape
    starts = np.empty(k, np.int64)
    carried = read_body(buf, body, ids, values, n, starts)
    if carried >= 0:
        for i in range(k):
            row = float32_at(buf, starts[i], n)
            for j in range(n):
                waveforms[i, j] = row[j]
    return carried


@kernel
def read_body(buf, body, ids, values, n, starts):
    """What a ``Sample``'s payload (the bytes ``buf``) holds that :func:`place_rows` reads, straight from the
    protobuf wire format from ``buf[body]`` on (the first field after its header, :func:`read_header`): γ
    measured and commanded, the motor's load, voltage and temperature and each reading's ``echo_valid, distance,
    time_of_flight`` into ``values`` (where :func:`place_rows` reads them; a field absent is 0, as the parser
    gives it), the first k carried energies after them, and where each waveform's samples start in ``buf`` into
    ``starts`` (its data field's bytes, read where they lie: :func:`~lelsonar.signal.compiled.float32_at`).

    Only a payload plainly encoded (each field read here once, with its own wire type, no groups, no header
    field after ``body``: the header read before it is then the parser's) on the fast path's layout (the k
    readings in the order of the capsule ``ids``, float32 waveforms of ``n`` samples each on the clocks in
    ``values[:2k]``, to the bit) is read; anything else, however valid, is left to the parsed message (-1;
    ``values`` and ``starts`` then partly written).

    Returns
    -------
    int
        How many energies the sample carries (≥ 0), or -1: not read.
    """
    bits = values.view(np.uint64)
    k = ids.size
    head, readings, energies = 2 * k, 2 * k + 5, 5 * k + 5
    # The fields around each waveform's samples — its reading's and its own before them, its clock after them —
    # are where the last sample of the layout had them, most likely: fetched together, not one after the other as
    # the walk finds each from the length before it.
    for j in range(starts.size):
        prefetch(buf, min(max(starts[j] - 64, 0), buf.size - 1))
        prefetch(buf, min(max(starts[j], 0), buf.size - 1))
        prefetch(buf, min(max(starts[j] + 4 * n, 0), buf.size - 1))
    # And the first waveform's first bytes: from there on the pass over the waveforms asks for the bytes ahead of
    # it itself (:func:`~lelsonar.reconstruct.stream.step_features.streamed_sums`).
    if starts.size:
        for q in range(64, STREAM_AHEAD, 64):
            prefetch(buf, min(max(starts[0] + q, 0), buf.size - 1))
    for j in range(head, head + 5):
        bits[j] = 0
    sensors = carried = seen = 0
    i, end = body, buf.size
    while i < end:
        field, wire_type, i = _wire_tag(buf, i, end)
        if i < 0 or field <= _SAMPLE_TIME:  # (a header field again: the parser keeps the last one)
            return -1
        if field == _SAMPLE_SENSORS:
            if wire_type != _LENGTH or sensors == k:
                return -1
            a, b = _wire_length(buf, i, end)
            if a < 0:
                return -1
            start = _read_reading(buf, a, b, np.uint64(ids[sensors]), bits, readings + 3 * sensors, 2 * sensors, n)
            if start < 0:
                return -1
            starts[sensors] = start
            sensors += 1
            i = b
        elif field == _SAMPLE_ENERGY:  # a repeated double: packed runs, or one at a time
            if wire_type == _FIXED64:
                a, b = i, i + 8
            elif wire_type == _LENGTH:
                a, b = _wire_length(buf, i, end)
            else:
                return -1
            if a < 0 or b > end or (b - a) % 8:
                return -1
            for j in range(a, b, 8):
                if carried < k:
                    bits[energies + carried] = _wire_fixed64(buf, j)
                carried += 1
            i = b
        elif field == _SAMPLE_GAMMA_MEASURED or field == _SAMPLE_GAMMA_COMMANDED:
            if wire_type != _FIXED64 or seen & (1 << field) or i + 8 > end:
                return -1
            bits[head if field == _SAMPLE_GAMMA_MEASURED else head + 1] = _wire_fixed64(buf, i)
            i += 8
            seen |= 1 << field
        elif field == _SAMPLE_MOTOR:
            if wire_type != _LENGTH or seen & (1 << field):
                return -1
            a, b = _wire_length(buf, i, end)
            if a < 0:
                return -1
            read = 0
            while a < b:
                f, w, a = _wire_tag(buf, a, b)
                if a < 0:
                    return -1
                if f == _MOTOR_LOAD or f == _MOTOR_VOLTAGE or f == _MOTOR_TEMPERATURE:
                    if w != _FIXED64 or read & (1 << f) or a + 8 > b:
                        return -1
                    bits[head + 2 + (0 if f == _MOTOR_LOAD else 1 if f == _MOTOR_VOLTAGE else 2)] = _wire_fixed64(
                        buf, a
                    )
                    a += 8
                    read |= 1 << f
                else:
                    a = _wire_skip(buf, a, b, w)
                    if a < 0:
                        return -1
            i = b
            seen |= 1 << field
        else:  # a field this build does not know
            i = _wire_skip(buf, i, end, wire_type)
            if i < 0:
                return -1
    return carried if sensors == k else -1


#: :func:`place_wire`'s ``arrays``, by index: the sample's steps' bound, the waveforms' length ``n``, the capsules
#: ``k``, the scan's rows, the timing and the candidate windows' widths, then the address of each array
#: :func:`wire_arrays` names, in its order.
_BOUND, _N, _K, _ROWS, _WIDTH, _KEPT, _ADDRESSES = 0, 1, 2, 3, 4, 5, 6
_PER_CAPSULE, _PER_STEP = len(PER_CAPSULE), len(PER_STEP)
_DT_INT64, _DT_FLOAT64, _DT_FLOAT32, _DT_BOOL = (np.dtype(t) for t in (np.int64, np.float64, np.float32, np.bool_))


def wire_arrays(
    bound: int,
    ids: np.ndarray,
    values: np.ndarray,
    n: int,
    starts: np.ndarray,
    scan: np.ndarray,
    per_capsule: np.ndarray,
    per_step: np.ndarray,
    acquired_ns: np.ndarray,
    received: np.ndarray,
    recovered_mask: np.ndarray,
    timing_windows: np.ndarray,
    candidate_windows: np.ndarray,
) -> np.ndarray:
    """:func:`place_wire`'s ``arrays``: the numbers and the addresses of :func:`place_rows`'s arrays after a sample's
    own (``ids``, ``values``, ``starts``, ``scan``: the layout's; the rest the scan's rows), one int64 array to hand
    over instead of a dozen (each array an argument costs a call its type's look-up and its buffer's unpacking).

    The addresses are valid while those arrays are: the caller keeps them with the result.

    Raises
    ------
    InternalError
        An array not of the shape, type or layout :func:`place_wire` reads it with.
    """
    k, rows, width = ids.size, received.size, timing_windows.shape[2]
    kept = candidate_windows.shape[2]
    expected = (
        (ids, _DT_INT64, (k,)),
        (values, _DT_FLOAT64, (6 * k + 5,)),
        (starts, _DT_INT64, (k,)),
        (scan, _DT_FLOAT64, (7,)),
        (per_capsule, _DT_FLOAT64, (_PER_CAPSULE, rows, k)),
        (per_step, _DT_FLOAT64, (_PER_STEP, rows)),
        (acquired_ns, _DT_INT64, (rows,)),
        (received, _DT_BOOL, (rows,)),
        (recovered_mask, _DT_BOOL, (rows,)),
        (timing_windows, _DT_FLOAT32, (rows, k, width)),
        (candidate_windows, _DT_FLOAT32, (rows, k, kept)),
    )
    for i, (array, dtype, shape) in enumerate(expected):
        flags = array.flags
        if (
            (array.dtype is not dtype and array.dtype != dtype)
            or array.shape != shape
            or not (flags.c_contiguous and flags.writeable)
        ):
            raise InternalError(
                f"place_wire's array {i} is {array.dtype}{array.shape} (contiguous {flags.c_contiguous}, writeable "
                f"{flags.writeable}); it reads {np.dtype(dtype)}{shape}, contiguous and writeable"
            )
    out = np.empty(_ADDRESSES + len(expected), np.int64)
    out[:_ADDRESSES] = bound, n, k, rows, width, kept
    _addresses(out, *(a for a, _, _ in expected))
    return out


@kernel
def _addresses(
    out, ids, values, starts, scan, per_capsule, per_step, acquired_ns, received, recovered, timing, candidates
):
    """Where each array's data lies, into ``out[_ADDRESSES:]`` in this order (one call, where ``.ctypes.data`` costs
    a Python object an array)."""
    out[_ADDRESSES] = ids.ctypes.data
    out[_ADDRESSES + 1] = values.ctypes.data
    out[_ADDRESSES + 2] = starts.ctypes.data
    out[_ADDRESSES + 3] = scan.ctypes.data
    out[_ADDRESSES + 4] = per_capsule.ctypes.data
    out[_ADDRESSES + 5] = per_step.ctypes.data
    out[_ADDRESSES + 6] = acquired_ns.ctypes.data
    out[_ADDRESSES + 7] = received.ctypes.data
    out[_ADDRESSES + 8] = recovered.ctypes.data
    out[_ADDRESSES + 9] = timing.ctypes.data
    out[_ADDRESSES + 10] = candidates.ctypes.data


@kernel
def place_wire(payload, at, step, time_ns, recovered, arrays):
    """:func:`place_rows` of a sample not validated, read from its ``payload``, and how many energies the sample
    carries and its step: ``(status, carried, step)``; ``(UNREAD, 0, step)`` if it could not be read that way, its
    step is already held or not below the bound (nothing placed), ``(GROW, 0, step)`` if the scan's arrays do not
    reach its step yet (nothing placed: grown, it is placed by the next call).

    From ``at`` on, the rest of its header (:func:`read_header`): ``step`` and ``acquisition_time_ns`` (else
    ``step`` and ``time_ns``, those read before ``at``), each at most once, no field that routes it again (the
    fields before ``at`` did); then its body (:func:`read_body`, into ``values``, and where its waveforms of ``n``
    samples lie into ``starts``: they are read there, never copied).  The sample's own arguments come first
    (``recovered``: its origin), then the scan's: ``arrays``, :func:`wire_arrays` of the arrays
    :func:`place_rows` takes (its numbers, and where each array lies, read there with
    :func:`~lelsonar.signal.compiled.array_at`)."""
    bound, n, k, rows = arrays[_BOUND], arrays[_N], arrays[_K], arrays[_ROWS]
    at_ = arrays[_ADDRESSES:]
    received = array_at(at_[7], rows, np.bool_)
    buf = unowned(np.frombuffer(payload, dtype=np.uint8))  # (handed on to every reader: the payload is held here)
    end = buf.size
    seen = 0
    body = at
    while body < end:
        field, wire_type, after = _wire_tag(buf, body, end)
        if after < 0 or field < _SAMPLE_STEP:
            return UNREAD, 0, step
        if field > _SAMPLE_TIME:
            break
        if wire_type != _VARINT or seen & (1 << field):
            return UNREAD, 0, step
        seen |= 1 << field
        v, body = _wire_varint(buf, after, end)
        if body < 0:
            return UNREAD, 0, step
        if field == _SAMPLE_STEP:
            if v >= np.uint64(1 << 32):
                return UNREAD, 0, step
            step = np.int64(v)
        else:
            time_ns = np.int64(v)  # (two's complement: the parser's int64)
    if step >= bound or (step < rows and received[step]):
        return UNREAD, 0, step
    if step >= rows:
        return GROW, 0, step
    prefetch_rows(at_[4], at_[5], at_[9], step, rows, k, arrays[_WIDTH])
    ids = array_at(at_[0], k, np.int64)
    values = array_at(at_[1], 6 * k + 5, np.float64)
    starts = array_at(at_[2], k, np.int64)
    carried = read_body(buf, body, ids, values, n, starts)
    if carried < 0:
        return UNREAD, 0, step
    return (
        place_rows(
            buf,
            starts,
            n,
            values,
            array_at(at_[3], 7, np.float64),
            k if carried == k else 0,
            step,
            False,
            time_ns,
            recovered,
            array_at(at_[4], (_PER_CAPSULE, rows, k), np.float64),
            array_at(at_[5], (_PER_STEP, rows), np.float64),
            array_at(at_[6], rows, np.int64),
            received,
            array_at(at_[8], rows, np.bool_),
            array_at(at_[9], (rows, k, arrays[_WIDTH]), np.float32),
            array_at(at_[10], (rows, k, arrays[_KEPT]), np.float32),
        ),
        carried,
        step,
    )


@kernel
def read_header(payload):
    """A ``Sample``'s header straight from its payload: whether it was read, ``schema_version``, the bounds
    (start, end) of ``scanner_id``'s bytes, ``scan_id``, ``step``, ``acquisition_time_ns``'s 64 bits, and where
    its body starts (the first field after the header, for :func:`read_body`), and where the fields that route
    it (``schema_version``, ``scanner_id``, ``scan_id``) end if they come first (0: not so).

    The header is the fields before the first field of another number: read only if each appears there at most
    once with its own wire type, its tags are ones the parser accepts and ``schema_version`` and ``step`` fit
    their 32 bits.  A field absent is 0, as the parser gives it.  Nothing after the header is touched (the
    body's fields lie in cache lines of their own): whether a header field comes again, as the parser would
    read it, is :func:`read_body`'s refusal.
    """
    buf = np.frombuffer(payload, dtype=np.uint8)
    version = scan_id = step = time = np.uint64(0)
    a = b = 0
    seen = 0
    routed = -1
    i, end = 0, buf.size
    while i < end:
        field, wire_type, after = _wire_tag(buf, i, end)
        if after < 0:
            return False, version, a, b, scan_id, step, time, i, 0
        if field > _SAMPLE_TIME:
            break
        if field >= _SAMPLE_STEP:
            routed = i if routed < 0 else routed
        elif routed >= 0:
            routed = 0  # a routing field after the others: no prefix routes it
        i = after
        if seen & (1 << field):
            return False, version, a, b, scan_id, step, time, i, 0
        seen |= 1 << field
        if field == _SAMPLE_SCANNER:
            if wire_type != _LENGTH:
                return False, version, a, b, scan_id, step, time, i, 0
            a, b = _wire_length(buf, i, end)
            if a < 0:
                return False, version, a, b, scan_id, step, time, i, 0
            i = b
            continue
        if wire_type != _VARINT:
            return False, version, a, b, scan_id, step, time, i, 0
        v, i = _wire_varint(buf, i, end)
        if i < 0:
            return False, version, a, b, scan_id, step, time, i, 0
        if field == _SAMPLE_VERSION:
            version = v
        elif field == _SAMPLE_SCAN:
            scan_id = v
        elif field == _SAMPLE_STEP:
            step = v
        else:
            time = v
    ok = version < np.uint64(1 << 32) and step < np.uint64(1 << 32)
    return ok, version, a, b, scan_id, step, time, i, i if routed < 0 else routed


def sample_header(payload: bytes) -> tuple[int, str, int, int, int, int, int] | None:
    """``(schema_version, scanner_id, scan_id, step, acquisition_time_ns, routed, body)`` of a ``Sample``'s
    payload (:func:`read_header`; ``routed``: where the fields that route it end if they come first, else 0;
    ``body``: where :func:`read_body` reads on), as the parser reads them if :func:`read_body` reads the body;
    None where the fast path leaves the payload to the parser (not plainly encoded, or a ``scanner_id`` that is
    not UTF-8)."""
    ok, version, a, b, scan_id, step, time, body, routed = read_header(payload)
    if not ok:
        return None
    try:
        scanner = payload[a:b].decode("utf-8")
    except UnicodeDecodeError:
        return None
    t = int(time)
    return int(version), scanner, int(scan_id), int(step), t - (1 << 64) if t >= 1 << 63 else t, routed, int(body)
