"""Readings that may be the noise a board's comparator fired on: the candidate echo after each, found as the
sample is placed (:func:`candidate_echo`), and which readings are noise, decided over the whole scan
(:class:`NoiseTriggers`).

A comparator set within a few σ of the noise fires on it at times; such a reading's range is the noise's
crossing, and its waveform shows no echo at its time of flight.  At ingest each reading that may be one keeps
its waveform around the first echo after it; at the final the scan's noise decides which readings are noise
(:meth:`NoiseTriggers.noise_triggers`), and the range repair recovers the echo after them
(:meth:`~lelsonar.reconstruct.stream.range_repair.RangeRepair.recovered_echoes`).
"""

from __future__ import annotations

import math

import numpy as np

from lelsonar.reconstruct.stream.scan_state import ScanState
from lelsonar.signal.compiled import kernel
from lelsonar.signal.echo_timing import FLOOR_TIME
from lelsonar.signal.energy import ECHO_PEAK_WINDOW, echoes_over_noise, ranges_backed, window_samples
from lelsonar.signal.extrema import extent

#: Fewest readings a scan-wide check of the ranges against the waveforms or the speed of sound rests on.
RANGE_CHECK_MIN = 16

#: A reading whose first :data:`~lelsonar.signal.energy.ECHO_PEAK_WINDOW` after its time of flight rises
#: (half its peak to peak) less than this over the same time before may be the noise a board's comparator fired
#: on: its first echo after is looked for (:func:`candidate_echo`).  The noise's crossing of a threshold within a
#: few σ of it stands ~1–2× over the noise before it (the largest of ~100 samples against the first crossing in
#: the ~1,000 the board listened to); an echo rises by its own signal-to-noise ratio.  Loose: which readings are
#: noise is decided at the final, over the scan's noise (:meth:`ScanAssembly.noise_triggers`).
CANDIDATE_RISE = 4.0
#: The candidate echo is where ``|w − DC|`` first reaches this many times the noise spike's own peak (the
#: largest ``|w − DC|`` over the spike's window): twice the level the noise reached once in the time the board
#: listened stands over it in the time after (Gaussian tails: z → 2z is a false alarm ~e^(−3z²/2) as likely),
#: while an echo a board would report stands well over its threshold.  An echo under that level is passed over
#: for the next one (a board with a higher threshold would report that one too); the final checks the echo
#: found stands over the scan's noise (:func:`~lelsonar.signal.energy.echoes_over_noise`).
CANDIDATE_LEVEL = 2.0


@kernel
def candidate_echo(row, a, width, rate):
    """The sample of ``row`` where the first echo after a time of flight that may be the noise a board fired on
    begins (:data:`CANDIDATE_RISE`, :data:`CANDIDATE_LEVEL`), as an offset from the timing window's first sample
    ``a`` (the window ``width`` samples wide, the time of flight in its middle); -1: not such a reading, or no
    echo after it.

    The DC level is the mean of the waveform from the window on (after the transmitter's ring-down, which the
    board's blanking leaves behind; an echo's carrier averages out).
    """
    n = row.size
    mid = a + width // 2
    span = window_samples(rate, ECHO_PEAK_WINDOW[0], ECHO_PEAK_WINDOW[1])
    if mid - span < a or mid + span > n:
        return -1
    lo_b, hi_b = extent(row, mid - span, mid)
    lo_a, hi_a = extent(row, mid, mid + span)
    if hi_a - lo_a >= CANDIDATE_RISE * (hi_b - lo_b):
        return -1  # an echo rises at the time of flight
    total = 0.0
    for j in range(a, n):
        total += row[j]
    dc = total / (n - a)
    spike = max(abs(hi_a - dc), abs(lo_a - dc))
    level = CANDIDATE_LEVEL * spike
    for j in range(mid + span, n):
        if abs(row[j] - dc) >= level:
            return j - a
    return -1


class NoiseTriggers(ScanState):
    """Which of a scan's readings are the noise a board fired on (a mixin of
    :class:`~lelsonar.reconstruct.stream.assembly.ScanAssembly`)."""

    def noise_triggers(self) -> tuple[np.ndarray, float]:
        """Which readings of the received steps (:meth:`arrays`' rows) show no echo over the noise at their time
        of flight (:func:`~lelsonar.signal.energy.echoes_over_noise`: a board whose comparator fired on
        the noise) nor have a neighbour's echo near their range (:func:`~lelsonar.signal.energy.
        ranges_backed`: a weak echo), and the noise σ (V; NaN: not known).  None where a reading's window was not
        kept (no waveform, or on another clock), nor with fewer than :data:`RANGE_CHECK_MIN` windows."""
        steps = np.flatnonzero(self.received)
        if self._noise_tested is not None and self._noise_tested[0] == len(steps):
            return self._noise_tested[1]  # steps only add up: the same count is the same steps
        at = self._timing_at[steps]
        kept = np.isfinite(at) & np.isfinite(self.distance[steps])
        noise = np.zeros(at.shape, bool)
        sigma = math.nan
        if np.count_nonzero(kept) >= RANGE_CHECK_MIN and self.sound_speed:
            distance = self.distance[steps]
            listened = 2.0 * distance[kept] / self.sound_speed
            echo = np.isfinite(distance)  # a reading without its window is not tested: taken as an echo
            rows, capsules = np.nonzero(kept)  # one gather of the kept windows, not a copy of every step's
            echo[kept], _, sigma = echoes_over_noise(
                self._timing_windows[steps[rows], capsules], self._timing_rate, at[kept], listened, FLOOR_TIME
            )
            # A weak echo beside a neighbour's stays: within the range one echo window spans.
            reach = 0.5 * self.sound_speed * (ECHO_PEAK_WINDOW[1] - ECHO_PEAK_WINDOW[0])
            noise = kept & ~echo & ~ranges_backed(distance, echo, reach)
        self._noise_tested = (len(steps), (noise, sigma))
        return noise, sigma

    def noise_independence(self) -> float:
        """How the ranges of the readings that mark no echo (:meth:`noise_triggers`) change from step to step: the
        median |difference| between a capsule's consecutive such readings over their spread (1.4826·MAD); NaN
        with fewer than :data:`RANGE_CHECK_MIN` differences.

        The noise's crossings are drawn anew at each reading (anywhere in the time the board listened, or all
        just after its blanking): about 1, as for independent draws.  A surface's ranges in another convention
        than the waveforms' times (a one-way time, a window's start left unset) change smoothly with the beam:
        next to 0.
        """
        noise, _ = self.noise_triggers()
        d = np.where(noise, self.distance[np.flatnonzero(self.received)], np.nan)
        jumps = np.abs(np.diff(d, axis=0))
        jumps = jumps[np.isfinite(jumps)]
        if jumps.size < RANGE_CHECK_MIN:
            return math.nan
        ranges = d[np.isfinite(d)]
        spread = 1.4826 * float(np.median(np.abs(ranges - np.median(ranges))))
        step = float(np.median(jumps))
        return step / spread if spread > 0 else (math.inf if step > 0 else 0.0)

    def noise_share(self) -> float:
        """The share of the received readings with a range that mark no echo (:meth:`noise_triggers`)."""
        readings = int(np.count_nonzero(np.isfinite(self.distance[self.received])))
        return np.count_nonzero(self.noise_triggers()[0]) / max(readings, 1)
