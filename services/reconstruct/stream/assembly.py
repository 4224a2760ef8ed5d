"""One scan, assembled from its messages in whatever order they arrive (no I/O).

Samples are placed by step index, so arrival order does not matter; a second
copy of a step is dropped.  Per step the assembly keeps what the math needs —
measured γ, ranges, the energy of each capsule (eq. 10), the first echo's
peak — and the latest step's waveforms, for display.

A sample is worked on once, as it is placed, in one compiled pass
(:func:`~lelsonar.reconstruct.stream.step_features.place_step`).  A sample for a
scan whose layout is known may arrive parsed but not validated
(:func:`~lelsonar.codec.parse`): the pass makes the contract's checks of its
readings and waveforms (its samples finite among them), leaving anything it does
not clear to :func:`~lelsonar.codec.validate_body`, which names the culprit.  A
``Sample`` may carry the energies its writer computed (``sensor_energy``, as the
acquisition service does); they are checked against the waveforms instead of
integrated again.  Where they disagree, or are not plausible, the energies are
recomputed, counted (:attr:`ScanAssembly.energy_mismatches`) and warned about;
without them (another writer) they are computed.  Either way the arrays hold
eq. (10) of the waveforms.  The acquisition service's samples (capsules in the
ScanStart's order, float32 waveforms of one length on one clock) go straight to
the pass; anything else another writer may send (its own capsule order and ids,
int16 data, a clock per capsule) is put in capsule order first (the general
path), to the same values.

What the scan's arrays say is read by the classes :class:`ScanAssembly` is built
on, one job each: :class:`~lelsonar.reconstruct.stream.scan_arrays.ScanArrays`
(the arrays, allocated and grown, and the latest step for display),
:class:`~lelsonar.reconstruct.stream.scan_state.ScanState`
(which steps arrived, the arrays of record),
:class:`~lelsonar.reconstruct.stream.candidates.NoiseTriggers` (readings that are
the noise a board fired on), :class:`~lelsonar.reconstruct.stream.range_repair.RangeRepair`
(ranges re-timed, echoes recovered) and
:class:`~lelsonar.reconstruct.stream.writer_checks.WriterChecks` (what the writer
stated otherwise than the contract).

The assembly knows which steps it lacks
(:meth:`ScanAssembly.missing_steps`) and where each step came from (the live
stream or the acquirer's log), for the per-scan accounting.
"""

from __future__ import annotations

import functools
import logging
import math
import struct

import numpy as np

from lelsonar import codec
from lelsonar.errors import InvalidMessageError, LelsonarError
from lelsonar.reconstruct.stream.fastwire import GROW, UNREAD, place_wire, wire_arrays
from lelsonar.reconstruct.stream.scan_arrays import ScanArrays, ScanDescription, StepView, stacked_waveforms
from lelsonar.reconstruct.stream.step_features import (
    AGREED,
    CANDIDATES,
    NO_SOUND_SPEED,
    UNCHECKED,
    place_step,
    settle_step,
)
from lelsonar.signal.compiled import entry_point
from lelsonar.signal.echo_timing import TIMING_WINDOW
from lelsonar.signal.energy import waveform_energy
from lelsonar.v1 import scan_pb2

__all__ = ["ScanAssembly", "StepView"]

_log = logging.getLogger(__name__)

_FLOAT32 = scan_pb2.WAVEFORM_ENCODING_FLOAT32_LE


@functools.lru_cache(maxsize=4)
def _placer(place):
    """``place`` (:func:`~lelsonar.reconstruct.stream.fastwire.place_wire`) called without Numba's dispatcher, for
    the arguments :meth:`ScanAssembly.add_payload` passes: a payload's ``bytes``, three ints, a bool and the
    scan's int64 array (:func:`~lelsonar.signal.compiled.entry_point`)."""
    return entry_point(place, b"", 0, 0, 0, False, np.zeros(1, np.int64))


@functools.lru_cache(maxsize=16)  # (k is bounded by DecodeLimits.max_sensors; a few sizes in practice)
def _packers(k: int) -> tuple[struct.Struct, struct.Struct]:
    """The packers of a sample's readings into the kernel's buffer of a scan of ``k`` capsules: γ, the motor and the
    readings, without and with the carried energies (one each a scan's size, not one a scan)."""
    return struct.Struct(f"<{5 + 3 * k}d"), struct.Struct(f"<{5 + 4 * k}d")


class ScanAssembly(ScanArrays):
    """One scan, assembled from its samples in whatever order they arrive."""

    def __post_init__(self, described: ScanDescription | None = None) -> None:
        super().__post_init__(described)
        # The kernel's constants of the scan (place_step's ``scan``): the speed of sound (NaN for none: the
        # ranges then need both fields), the timing windows' rate (NaN until the first waveforms), E0's model.
        model = self.energy_model
        self._scan = np.array(
            [
                math.nan if self.sound_speed is None else float(self.sound_speed),
                math.nan,
                model.phi0,
                model.phi1,
                model.phi2,
                model.d_min,
                model.d_max,
            ]
        )
        # The fast path's layout (the readings' capsule ids, lengths and clocks), once a sample has shown it, and
        # the kernel's buffer of numbers (place_step's ``values``): the layout's clocks, then each sample's
        # readings and energies, packed straight from the decoded lists (cheaper than a new array a sample).
        self._layout: list | None = None
        self._limits_cleared: codec.DecodeLimits | None = None  # the limits the layout and schedule are within
        self._buffer = bytearray(8 * (6 * self._k + 5))
        self._values = np.frombuffer(self._buffer, dtype=np.float64)
        self._pack_readings, self._pack_readings_energies = _packers(self._k)
        # Where fastwire.place_wire finds each waveform's samples in a sample's payload (read there, never copied).
        self._starts = np.zeros(self._k, np.int64)
        # The layout of the scanner's previous scan (:meth:`expect_layout`), tried on this scan's first sample.
        self._expected: list | None = None

    @property
    def layout(self) -> list | None:
        """The fast path's layout once a validated sample of this scan showed it (each reading's capsule id, samples,
        rate, t0, encoding and bytes, in capsule order: :func:`~lelsonar.codec.sample_readings`); None: none yet."""
        return self._layout

    def expect_layout(self, layout: list | None) -> None:
        """Try ``layout`` — the :attr:`layout` of the scanner's previous scan, validated there — on this scan's first
        sample: read straight from its payload if it has that layout (:meth:`add_payload`), as every later one is.
        Nothing changes until then; a first sample on another layout, or not read that way, leaves the scan as if
        this had never been called (it is then parsed, and shows the scan its own layout)."""
        self._expected = layout

    def _presume(self) -> list | None:
        """Set the expected layout up as a first sample on it does (:meth:`add`: the layout, the kernel's clocks,
        the timing windows' rate); None (nothing set) if there is none, or it is not this scan's."""
        layout = self._expected
        if layout is None or self.received.any() or not self._one_layout(layout):
            return None
        rate = layout[2]
        if layout[1] and rate > 0 and math.isfinite(rate):
            self._timing_rate = self._scan[1] = float(rate)
            self._grow_timing(len(self.received), max(int(round((TIMING_WINDOW[1] - TIMING_WINDOW[0]) * rate)), 1))
        return layout

    def _unpresume(self) -> None:
        """Undo :meth:`_presume` (its first sample was not read on that layout): the scan as before it."""
        self._layout = self._limits_cleared = self._wire = None
        self._values[: 2 * self._k] = 0.0
        self._timing_rate = self._scan[1] = math.nan
        self._grow_timing(len(self.received), 0)

    def add_payload(
        self, payload: bytes, at: int, step: int, time_ns: int, origin: str, limits: codec.DecodeLimits
    ) -> int:
        """Place a sample straight from its ``payload`` (:mod:`~lelsonar.reconstruct.stream.fastwire`), never
        parsed: its header read up to ``at`` (``step`` and ``acquisition_time_ns`` if they came before it, else
        0, as the parser gives a field absent), the rest of it and its body from there; its body's checks under
        ``limits`` are made in the pass that places it (:func:`~lelsonar.reconstruct.stream.step_features.
        place_rows`).  Only on the layout of a sample validated before (the same ids, encodings, lengths and
        clocks: the contract's checks of them passed), of this scan or, for its first, of the scanner's previous
        one (:meth:`expect_layout`).  Returns the step placed, or -1: anything this does not
        clear — no layout yet, a payload not plainly encoded on it, a refused check, a duplicate or a step
        outside the schedule — is left with nothing written: the caller then parses the payload and places the
        message (:meth:`add`), so that the decoding refuses before the scan does.

        Raises
        ------
        InvalidMessageError
            A range that needs a speed of sound the scan does not state.
        """
        if type(payload) is not bytes:  # (the type the placer was compiled for)
            payload = bytes(payload)
        wire = self._wire
        presumed = False
        if wire is None or limits is not self._limits_cleared:  # (the common case is neither)
            if self._layout is None:  # the scan's first sample: on the scanner's previous layout, or parsed
                if self._presume() is None:
                    return -1
                presumed = True
            wire = self._wire if limits is self._limits_cleared else None
            if wire is None:
                wire = self._wire_for(limits)
                if wire is None:
                    return self._placed_payload(UNREAD, 0, step, payload, presumed)
        recovered = origin == "recovered"
        while True:
            # (A step already held is the kernel's refusal: the parser's path then counts the duplicate.)
            status, carried, step = wire[2](payload, at, step, time_ns, recovered, wire[0])
            if status == AGREED:  # what _placed leaves to do is to note the latest step
                self._latest = (step, payload, self._layout)
                return step
            if status != GROW:
                return self._placed_payload(status, carried, step, payload, presumed)
            self._allocate(min(self._steps, max(2 * len(self.received), step + 1)))
            wire = self._wire_for(limits)  # placed once the arrays reach its step (the same limits: not None)
            if wire is None:
                return self._placed_payload(UNREAD, 0, step, payload, presumed)

    def _placed_payload(self, status: int, carried: int, step: int, payload: bytes, presumed: bool) -> int:
        """:meth:`add_payload`'s result of a placement's ``status`` other than ``AGREED`` (:meth:`_placed`);
        ``presumed``: the layout was presumed for this sample (:meth:`_presume`), undone if it was not read on it."""
        known = self._layout
        if known is None or (status < 0 and status != NO_SOUND_SPEED):  # (UNREAD, UNCHECKED; no layout: not read)
            if presumed:
                self._unpresume()
            return -1
        return step if self._placed(status, carried, step, payload, known, None, True, payload) else -1

    def _wire_for(self, limits: codec.DecodeLimits) -> tuple | None:
        """The argument of :func:`~lelsonar.reconstruct.stream.fastwire.place_wire` after a sample's own under
        ``limits`` (:func:`~lelsonar.reconstruct.stream.fastwire.wire_arrays` of its steps' bound, the layout and
        the scan's arrays) and those arrays, which it points into; kept while the scan's limits and arrays stay;
        None: no layout yet, or one beyond ``limits``."""
        known = self._layout
        if known is None:
            return None
        cleared = limits is self._limits_cleared or self._clears(limits)
        if cleared:
            bound = self._steps
        elif self._k <= limits.max_sensors and known[1] <= limits.max_waveform_samples:
            # A schedule beyond the limits (its ScanStart validated under others): each step checked against them.
            bound = min(self._steps, limits.max_steps)
        else:
            return None
        arrays = (bound, self._ids, self._values, known[1], self._starts, self._scan, *self._arrays())
        wire = (wire_arrays(*arrays), arrays, _placer(place_wire))  # (the arrays kept with their addresses)
        if cleared:
            self._wire = wire
        return wire

    def _clears(self, limits: codec.DecodeLimits) -> bool:
        """Whether every step of the scan's schedule, its capsules and its layout's waveform length are within
        ``limits`` (which a ScanStart validated under other limits does not bound); if so, they are remembered as
        cleared for the samples that follow."""
        if not (
            self._steps <= limits.max_steps
            and self._k <= limits.max_sensors
            and self._layout is not None
            and self._layout[1] <= limits.max_waveform_samples
        ):
            return False
        self._limits_cleared = limits
        return True

    def add(
        self,
        sample: codec.Sample,
        origin: str = "live",
        *,
        limits: codec.DecodeLimits | None = None,
    ) -> bool | None:
        """Place a sample (``origin`` "live" or "recovered"); return False for a duplicate step.

        ``limits``: the sample's body has not been validated (:func:`~lelsonar.codec.parse` only); its checks
        under ``limits`` are made here, on the acquisition service's layout in the pass that places it
        (:func:`~lelsonar.reconstruct.stream.step_features.place_step`).  Anything that pass does not clear — a
        layout other than the one last placed, a refused check, a duplicate or a step outside the schedule —
        returns None with nothing written: the caller then validates the sample
        (:func:`~lelsonar.codec.validate_body`, which names the culprit) and adds it again without ``limits``,
        so that the decoding refuses before the scan does.

        Raises
        ------
        InvalidMessageError
            A step outside the schedule, capsules the ScanStart did not list, waveforms of different lengths,
            or a range that needs a speed of sound the scan does not state.
        """
        step = sample.step
        received = self.received
        if step >= self._steps or (step < len(received) and received[step]):
            if limits is not None:
                return None
            if step >= self._steps:
                raise InvalidMessageError(f"step {step} is outside the schedule of {self._steps} steps")
            self.duplicates += 1
            self._compare_copy(sample, step, origin)
            return False
        k = self._k
        known = self._layout
        if limits is not None:
            # Only on the layout of a sample validated before (the same ids, encodings, lengths and clocks: the
            # contract's checks of them passed) but for its checks against ``limits``, made here.
            if known is None or not (
                step < limits.max_steps and k <= limits.max_sensors and known[1] <= limits.max_waveform_samples
            ):
                return None
        ranges, layout, data = codec.sample_readings(sample.sensors)
        # The fast path, for what the acquisition service sends: the capsules in the ScanStart's order, float32
        # waveforms of one length on one clock (the layout of the previous such sample, or checked here).
        # Anything else (another writer's order, int16 data, a clock per capsule) takes the general path, to
        # the same values.
        fast = layout == known
        if limits is not None and not fast:
            return None
        if step >= len(received):
            self._allocate(min(self._steps, max(2 * len(received), step + 1)))
        if not layout:
            raise InvalidMessageError(f"sample {step} carries no sensor readings")
        n = layout[1]
        carried = sample.sensor_energy[:]  # a list: cheaper to slice out than to unpack the field
        m = len(carried)
        gamma = sample.gamma_measured
        motor = sample.motor
        if fast or self._one_layout(layout):
            # The readings into the kernel's buffer, after the clocks (the layout's, written there once).
            if m == k:
                self._pack_readings_energies.pack_into(
                    self._buffer,
                    16 * k,
                    gamma,
                    sample.gamma_commanded,
                    motor.load,
                    motor.voltage,
                    motor.temperature,
                    *ranges,
                    *carried,
                )
            else:  # not one a waveform: not the waveforms' energies (recomputed and counted below)
                self._pack_readings.pack_into(
                    self._buffer,
                    16 * k,
                    gamma,
                    sample.gamma_commanded,
                    motor.load,
                    motor.voltage,
                    motor.temperature,
                    *ranges,
                )
            values, joined, one_clock = self._values, b"".join(data), True
        else:
            sensors, in_order = self._in_capsule_order(sample, carried if m == k else None)
            ranges, layout, data = codec.sample_readings(sensors)
            joined = np.ascontiguousarray(stacked_waveforms([s.waveform for s in sensors], n), dtype="<f4").tobytes()
            clocks = [v for i in range(k) for v in layout[6 * i + 2 : 6 * i + 4]]  # (rate, t0) of each
            one_clock = clocks == [layout[2], layout[3]] * k
            carried_list = [] if in_order is None else in_order
            values = np.array(
                [
                    *clocks,
                    gamma,
                    sample.gamma_commanded,
                    motor.load,
                    motor.voltage,
                    motor.temperature,
                    *ranges,
                    *carried_list,
                ],
                dtype=np.float64,
            )
        waveforms = np.frombuffer(joined, dtype=np.float32).reshape(k, n)
        if not self._timing_windows.shape[2] and n and values[0] > 0 and math.isfinite(values[0]):
            # The first sample with waveforms sets the windows' rate.
            self._timing_rate = self._scan[1] = float(values[0])
            self._grow_timing(
                len(self.received), max(int(round((TIMING_WINDOW[1] - TIMING_WINDOW[0]) * self._timing_rate)), 1)
            )
        status = place_step(
            waveforms,
            values,
            self._scan,
            k if m == k else 0,
            step,
            limits is None,
            sample.acquisition_time_ns,
            origin == "recovered",
            *self._arrays(),
        )
        return self._placed(status, m, step, waveforms, layout, ranges, one_clock, waveforms)

    def _compare_copy(self, sample: codec.Sample, step: int, origin: str) -> None:
        """A second copy of a held step: identical, or a conflict; a copy from the acquirer's log settles it.

        The copy is placed in a scratch scan and compared on what the estimate reads (time, angle, ranges,
        energies): only duplicates pay for it.
        """
        probe = ScanAssembly(self.start)
        try:
            probe.add(sample, origin)
            differs = probe.time_ns[step] != self.time_ns[step] or not all(
                np.allclose(getattr(probe, name)[step], getattr(self, name)[step], rtol=1e-9, atol=0, equal_nan=True)
                for name in ("gamma", "gamma_commanded", "distance", "sensor_energy", "echo_amplitude")
            )
        except LelsonarError:
            differs = True
        if origin == "recovered":  # the log is the truth: its copy stays
            if differs:
                self.received[step] = False
                self._timed[step] = False
                self._walk_tested = self._noise_tested = self._recovered = None
                self.add(sample, origin)
                self.replaced += 1
            self.unsettled.discard(step)
        elif differs:
            self.conflicts += 1
            self.unsettled.add(step)

    def _placed(
        self,
        status: int,
        carried: int,
        step: int,
        waveforms: np.ndarray | bytes,
        layout: list,
        ranges: list | None,
        one_clock: bool,
        latest,
    ) -> bool | None:
        """What a step's placement (:func:`~lelsonar.reconstruct.stream.step_features.place_step`'s ``status``)
        leaves to do, rarely anything: a refusal, energies to recompute (``carried``: how many the sample
        carries), ranges without an echo to count; the step is then the latest (``latest``: its waveforms, or
        the payload to read them from).  ``waveforms``: the (k, n) float32 array, or the payload they lie in (on
        the fast path's layout), parsed only if they are needed.  ``layout``, ``ranges``: the sample's in the order
        of the capsules (``ranges`` None: read from the kernel's buffer, where the fast path put them)."""
        if isinstance(waveforms, bytes) and status >= 0 and (status & CANDIDATES or not status & AGREED):
            waveforms = stacked_waveforms([s.waveform for s in codec.parse(waveforms, codec.Sample).sensors], layout[1])
        if status > 0 and status & CANDIDATES:
            status &= ~CANDIDATES
            self._keep_candidates(step, np.asarray(waveforms), layout)
        if status != AGREED:
            if status == UNCHECKED:
                return None
            if status == NO_SOUND_SPEED:
                if ranges is None:
                    ranges = self._values[2 * self._k + 5 : 5 * self._k + 5].tolist()
                self._no_sound_speed(step, ranges, layout)
            if not status & AGREED:
                waves = np.asarray(waveforms)
                self.sensor_energy[step] = (
                    waveform_energy(waves, layout[2])
                    if one_clock
                    else [waveform_energy(wv, r) for wv, r in zip(waves, layout[2::6])]
                )
                settle_step(self._per_capsule, self._per_step, step, self._scan)  # of these energies
                if carried:
                    self._energy_mismatch(step)
            self.unflagged_ranges += status >> 1
        self._latest = (step, latest, layout)
        return True

    def _keep_candidates(self, step: int, waveforms: np.ndarray, layout: list) -> None:
        """Allocate the candidate echoes' windows (the first step with one: a clean scan never holds them) and
        copy step ``step``'s from its ``waveforms`` ((k, n) float32 in capsule order, each on its ``layout``'s
        clock), where the pass found them (``_candidate_start``)."""
        width = self._timing_windows.shape[2]
        self._candidate_windows = np.zeros((len(self.received), self._k, width), np.float32)
        self._wire = None
        for i in np.flatnonzero(np.isfinite(self._candidate_at[step])):
            c0 = int(round((self._candidate_start[step, i] - layout[6 * i + 3]) * self._timing_rate))
            self._candidate_windows[step, i] = waveforms[i, c0 : c0 + width]

    def _one_layout(self, layout: list) -> bool:
        """Whether a validated sample's layout is the fast path's (the ScanStart's capsule ids in order, float32
        waveforms of one length on one clock); if it is, it is the one to expect next, and its clocks are
        written into the kernel's buffer."""
        k = self._k
        _, n, rate, t0 = layout[:4]
        if not (
            len(layout) == 6 * k
            and layout[::6] == self._capsule_ids
            and layout[1::6] == [n] * k
            and layout[2::6] == [rate] * k
            and layout[3::6] == [t0] * k
            and layout[4::6] == [_FLOAT32] * k
            and layout[5::6] == [4 * n] * k
        ):
            return False
        self._values[: 2 * k] = [rate, t0] * k
        self._layout = layout
        self._limits_cleared = None
        self._wire = None
        return True

    def _no_sound_speed(self, step: int, ranges: list, layout: list) -> None:
        for i in range(0, len(ranges) // 3):
            valid, d, t = ranges[3 * i : 3 * i + 3]
            if valid and not (d > 0 and t > 0):
                raise InvalidMessageError(
                    f"sample {step} capsule {layout[6 * i]} gives only its {'distance' if d > 0 else 'time of flight'}"
                    " and the ScanStart states neither sound_speed nor air_temperature to convert it: "
                    "fill both fields of the reading, or ScanStart.sound_speed"
                )

    def _energy_mismatch(self, step: int) -> None:
        self.energy_mismatches += 1
        if self.energy_mismatches == 1:  # once a scan; the rest are counted
            _log.warning(
                "scan %s: the sensor_energy carried by step %d disagrees with its waveforms (or is not "
                "one finite, non-negative value per capsule); recomputed from the waveforms; further "
                "such steps of this scan are counted in energy_mismatches",
                self.key,
                step,
            )

    def _in_capsule_order(self, sample: codec.Sample, carried: list[float] | None) -> tuple[list, list[float] | None]:
        """The sensors of a sample in the order of the ScanStart's capsule ids, and the carried energies in
        the same order; checked (the capsules the ScanStart listed, waveforms of one length)."""
        sensors = list(sample.sensors)
        ids = [s.capsule_id for s in sensors]
        if ids != self._capsule_ids:
            if sorted(ids) != self._capsule_ids:
                raise InvalidMessageError(
                    f"sample {sample.step} carries capsules {ids}; the scan has capsules {self._capsule_ids}"
                )
            order = sorted(range(len(ids)), key=ids.__getitem__)
            sensors = [sensors[i] for i in order]
            if carried is not None and len(carried) == len(order):  # carried in the order of the sensors
                carried = [carried[i] for i in order]
        counts = {s.waveform.sample_count for s in sensors}
        if len(counts) > 1:
            raise InvalidMessageError(f"sample {sample.step} has waveforms of different lengths {sorted(counts)}")
        return sensors, carried
