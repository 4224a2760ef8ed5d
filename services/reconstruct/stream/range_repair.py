"""Range repair: ranges re-timed from the waveforms where the writer's walk with the echoes' amplitude, and the
echo after each reading the board fired on noise recovered from its waveform.

Both rest on the waveform windows kept as each sample is placed
(:mod:`~lelsonar.reconstruct.stream.step_features`), and on whether the readings' times of flight fall where
their waveforms' echoes begin (:meth:`RangeRepair.ranges_match_waveforms`).
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from lelsonar.reconstruct.estimate.robust import fast_median, median
from lelsonar.reconstruct.stream.candidates import RANGE_CHECK_MIN, NoiseTriggers
from lelsonar.reconstruct.stream.comparator_level import envelope_at, fires_up_the_edge
from lelsonar.reconstruct.stream.step_features import RISE_STRIDE
from lelsonar.signal.echo_timing import (
    FLOOR_TIME,
    MIN_TIMED,
    RangeWalk,
    echo_onsets,
    range_walk,
    typical_edges,
    walk_free_ranges,
)
from lelsonar.signal.energy import echo_amplitude, echoes_over_noise, noise_level

#: Smallest median ratio of an echo's peak (:data:`~lelsonar.signal.energy.ECHO_PEAK_WINDOW` after the
#: time of flight) to the peak just before it (``PRE_ECHO_WINDOW``) for the ranges to match the waveforms.
#: A comparator fires on an echo's rising edge, over a threshold well above the noise: the echo's peak is
#: several times what precedes it.  A time of flight off by a factor (one-way, or a range taken for the round
#: trip) puts both windows on noise or inside one echo: a ratio near 1.
MIN_ECHO_RISE = 1.5
#: Smallest step-to-step change of the noise triggers' ranges over their spread (:meth:`ScanAssembly.
#: noise_independence`) for most readings marking no echo to be a board firing on the noise rather than ranges
#: in another convention: halfway between independent draws' ~1 and a surface's ~0.
NOISE_INDEPENDENT = 0.5


class RangeRepair(NoiseTriggers):
    """Ranges re-timed and echoes recovered from the kept waveforms (a mixin of
    :class:`~lelsonar.reconstruct.stream.assembly.ScanAssembly`)."""

    def range_walk(self) -> tuple[RangeWalk, np.ndarray, np.ndarray, np.ndarray]:
        """Whether the writer's ranges walk with the echoes' amplitude (:func:`~lelsonar.signal.echo_timing.
        range_walk`, on the echoes of a typical shape, where the writer's times lie up their rising edges as a
        comparator's do: :meth:`_fires_up_the_edge`), and each received step's offsets (writer's range −
        re-timed, m; NaN: not timed), peaks (V; NaN: no echo found) and whether its shape is typical
        (:func:`~lelsonar.signal.echo_timing.typical_edges`)."""
        steps = np.flatnonzero(self.received)
        if self._walk_tested is not None and self._walk_tested[0] == len(steps):
            return self._walk_tested[1]  # steps only add up: the same count is the same steps

        def test(rows: np.ndarray, halves: bool) -> tuple[RangeWalk, np.ndarray, np.ndarray, np.ndarray]:
            onset, peak, edge = np.moveaxis(self._echo_timing[rows], -1, 0)
            typical = typical_edges(edge)
            offset = -0.5 * (self.sound_speed or math.nan) * onset
            shown = typical | np.isnan(onset)  # clipped echoes count as found but untimed
            walk = range_walk(np.where(typical, offset, np.nan), np.where(shown, peak, np.nan), halves=halves)
            return walk, offset, peak, typical

        # A screen on the checked steps (a quarter of the echoes: the re-timing is spared on
        # the others where nothing walks), then the test on every step where the screen found a walk.
        checked = steps[steps % RISE_STRIDE == 0]
        self._time_echoes(checked)
        found = test(checked, False)
        if not found[0].detected:
            found = (
                found[0],
                *(np.full(self.distance[steps].shape, np.nan),) * 2,
                np.zeros(self.distance[steps].shape, bool),
            )
        else:
            self._time_echoes(steps)
            found = test(steps, True)
            if found[0].detected and not self._fires_up_the_edge(steps, found[3]):
                found = (replace(found[0], detected=False), *found[1:])
        self._walk_tested = (len(steps), found)  # the final's ranges and its planes' reasons ask it in turn
        return found

    def _fires_up_the_edge(self, steps: np.ndarray, typical: np.ndarray) -> bool:
        """Whether the writer's times of the typical echoes of ``steps`` lie up their rising edges, as a threshold
        comparator's do (:func:`~lelsonar.reconstruct.stream.comparator_level.fires_up_the_edge`): a walk the
        constant-fraction times show on a board that times the onset is theirs, not the writer's."""
        rows, capsules = np.nonzero(typical)
        at = self._timing_at[steps[rows], capsules]
        level, sigma = envelope_at(self._timing_windows[steps[rows], capsules], self._timing_rate, at)
        return fires_up_the_edge(level, sigma, self._echo_timing[steps[rows], capsules, 1])

    def _time_echoes(self, steps: np.ndarray) -> None:
        """Re-time (:func:`~lelsonar.signal.echo_timing.echo_onsets`) the kept windows of ``steps`` not
        timed yet."""
        todo = steps[~self._timed[steps]]
        at = self._timing_at[todo]
        kept = np.isfinite(at)
        if kept.any():
            timing = np.full((*at.shape, 3), np.nan)
            rows, capsules = np.nonzero(kept)
            windows = self._timing_windows[todo[rows], capsules]
            timing[kept] = np.stack(echo_onsets(windows, self._timing_rate, at[kept]), axis=-1)
            self._echo_timing[todo] = timing
        self._timed[todo] = True

    def walk_free(self, distance: np.ndarray) -> np.ndarray:
        """:meth:`arrays`' ``distance`` re-timed from the waveforms where the writer's ranges walk with the
        echoes' amplitude (:func:`~lelsonar.signal.echo_timing.walk_free_ranges`), else as it is."""
        walk, offset, peak, _ = self.range_walk()
        return walk_free_ranges(distance, offset, peak, walk)

    def echo_rise(self) -> tuple[float, float]:
        """The median over the checked readings of the first echo's peak over the peak just before it (both
        above the waveform's DC level): over all of them, and over those with an echo over the noise
        (:meth:`noise_triggers`); NaN with fewer than :data:`RANGE_CHECK_MIN` readings.  Under
        :data:`MIN_ECHO_RISE` the ranges do not match the waveforms (:meth:`ranges_match_waveforms`)."""
        got = self.received
        # Both peaks above the waveform's DC level (max |w| of a carrier burst or of noise over an offset is
        # |offset| + its own peak): a receiver's offset would otherwise pull the rise towards 1.
        dc = self.dc_level[got]
        with np.errstate(divide="ignore", invalid="ignore"):
            rise = (self.echo_amplitude[got] - dc) / (self.pre_echo_peak[got] - dc)
        checked = np.isfinite(rise)
        with_echo = checked & ~self.noise_triggers()[0]
        whole, echoes = (
            fast_median(rise[m]) if np.count_nonzero(m) >= RANGE_CHECK_MIN else math.nan for m in (checked, with_echo)
        )
        return whole, echoes

    def ranges_match_waveforms(self) -> bool:
        """Whether the readings' times of flight fall where their waveforms' echoes begin (:meth:`echo_rise`).

        Those readings with an echo over the noise decide: a board whose comparator fires on the noise before
        some echoes leaves the others' ranges right (those are re-timed from the echo after them or left out,
        :meth:`noise_triggers_recovered`),
        while ranges in another convention than the waveforms (a one-way time, a window's start left unset)
        put next to none of them at an echo's onset.  Too few of them to tell, the scan's readings as a whole
        decide (none to check: they match).
        """
        whole, echoes = self.echo_rise()
        return echoes >= MIN_ECHO_RISE if math.isfinite(echoes) else not whole < MIN_ECHO_RISE

    def recovered_echoes(self) -> tuple[np.ndarray, np.ndarray]:
        """The ranges (m) and peaks (V, :func:`~lelsonar.signal.energy.echo_amplitude`'s) of the first echo
        after each reading the board fired on noise (:meth:`noise_triggers`; :meth:`arrays`' rows, NaN where
        none), from its waveform.

        At ingest each reading that may be noise kept its waveform around the first echo after its time of
        flight (:func:`~lelsonar.reconstruct.stream.candidates.candidate_echo`).  That echo is recovered if it
        stands over the scan's noise as an echo at a board's time of flight must
        (:func:`~lelsonar.signal.energy.echoes_over_noise`, the scan's DC level and σ, over the samples
        listened to until it), and is timed where a board would time
        it: by constant fraction (:func:`~lelsonar.signal.echo_timing.echo_onsets`, a time that does not
        walk with its strength), with the board's zero where the scan's echoes show it (their ranges less
        their constant-fraction times over the strongest quarter, :attr:`~lelsonar.signal.echo_timing.
        RangeWalk.reference`, as :meth:`walk_free` keeps it), else at the strongest recovered echoes' crossing
        of the noise's level (:func:`~lelsonar.signal.energy.noise_level`) — a comparator set within a
        few σ of the noise, as this board's, fires near there on a strong echo.  An echo clipped at its peak
        (no fraction of it its own) is strong: timed at that crossing.  One not found or too weak to time
        stays out."""
        steps = np.flatnonzero(self.received)
        if self._recovered is not None and self._recovered[0] == len(steps):
            return self._recovered[1]
        noise, _ = self.noise_triggers()
        distance, peak = np.full(noise.shape, np.nan), np.full(noise.shape, np.nan)
        at, start = self._candidate_at[steps], self._candidate_start[steps]
        rows = noise & np.isfinite(at)
        if np.count_nonzero(rows) >= RANGE_CHECK_MIN and self.sound_speed:
            rate = self._timing_rate
            picked, capsules = np.nonzero(rows)  # one gather of these windows, not a copy of every step's
            windows = self._candidate_windows[steps[picked], capsules]
            at, start = at[rows], start[rows]
            # The noise over these windows' own floors: the time-of-flight windows' may lie in the transmitter's
            # ring-down, where a board that fires on the noise as soon as its blanking ends puts them.
            echo, _, sigma = echoes_over_noise(windows, rate, at, start + at, FLOOR_TIME)
            self._recovery_sigma = sigma
            onset, envelope, _ = echo_onsets(windows, rate, at)
            # Where each echo's envelope rises through the noise's level (clipped echoes too: strong ones).
            crossing = echo_onsets(windows, rate, at, level=noise_level(sigma, start + at, rate))[0]
            timed = echo & np.isfinite(onset) & np.isfinite(crossing)
            level_zero = 0.0
            if timed.any():
                # The strongest quarter's crossing of the noise's level, as a board set near it times them.
                strong = timed & (envelope >= np.percentile(envelope[timed], 75.0))
                level_zero = median(crossing[strong] - onset[strong])
            # An echo clipped at its peak (no fraction of it to time) is strong: its crossing, less that zero.
            cf = np.where(timed, onset, np.where(echo & np.isfinite(crossing), crossing - level_zero, np.nan))
            walk = self.range_walk()[0] if self.ranges_match_waveforms() else None
            if walk is not None and walk.n >= MIN_TIMED:
                # The scan's echoes give the board's own zero: its ranges less their constant-fraction ones over
                # the strongest quarter (RangeWalk.reference), as the re-timed ranges keep it (walk_free_ranges).
                distance[rows] = 0.5 * self.sound_speed * (start + at + cf) + walk.reference
            else:
                distance[rows] = 0.5 * self.sound_speed * (start + at + cf + level_zero)
            amplitude = echo_amplitude(windows, rate, 0.0, at)
            peak[rows] = np.where(np.isfinite(cf), amplitude, np.nan)
        self._recovered = (len(steps), (distance, peak))
        return distance, peak

    def noise_triggers_recovered(self, distance: np.ndarray, amplitude: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`arrays`' ``distance`` and the echoes' peaks (``amplitude``) with the readings that mark no echo
        (:meth:`noise_triggers`) replaced by the echo after them (:meth:`recovered_echoes`; NaN where none), if
        the scan's ranges otherwise match its waveforms (:meth:`ranges_match_waveforms`) or most readings are
        noise (:meth:`noise_share`) whose ranges change from step to step as the noise's crossings do
        (:meth:`noise_independence`: a board firing on the noise, not ranges in another convention than the
        waveforms); unchanged otherwise (nothing the readings mark can be told from noise: the scan is
        unreliable as a whole, :meth:`writer_problems`)."""
        noise, _ = self.noise_triggers()
        if not noise.any() or not (
            self.ranges_match_waveforms() or self.noise_share() > 0.5 and self.noise_independence() > NOISE_INDEPENDENT
        ):
            return distance, amplitude
        found, peak = self.recovered_echoes()
        return np.where(noise, found, distance), np.where(noise, peak, amplitude)
