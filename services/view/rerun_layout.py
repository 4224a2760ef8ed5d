"""The Rerun recording's frame: its timelines, the recording stream and the default layout.

:mod:`lelsonar.view.rerun_log` writes the entities (its module doc lists the paths);
this module names the timelines they are logged on and lays the views out over them.
"""

from __future__ import annotations

import rerun as rr
import rerun.blueprint as rrb

__all__ = ["STEP_TIMELINE", "ANGLE_TIMELINE", "TIME_TIMELINE", "make_recording", "join_path", "default_blueprint"]

STEP_TIMELINE = "step"
#: γ in hundredths of a degree (a sequence timeline, see :mod:`lelsonar.view.rerun_log`).
ANGLE_TIMELINE = "gamma_cdeg"
TIME_TIMELINE = "acq_time"


def make_recording(application_id: str = "lelsonar", recording_id: str | None = None) -> rr.RecordingStream:
    """A new recording stream without sinks.

    Parameters
    ----------
    application_id : str
        Groups recordings in the viewer.
    recording_id : str or None
        Recordings with the same id are merged by the viewer; ``None`` makes a
        fresh random one.

    Returns
    -------
    rerun.RecordingStream
        Give it sinks before logging, e.g. ``rec.save(path,
        default_blueprint=default_blueprint())``, ``rec.serve_grpc()``,
        ``rec.spawn()`` or ``rec.set_sinks(rr.FileSink(path))``; data logged
        before that is buffered.
    """
    return rr.RecordingStream(application_id, recording_id=recording_id)


def join_path(root: str, *parts: str) -> str:
    """``root`` + ``parts`` as an entity path (parts are already escaped)."""
    base = "/" + root.strip("/") if root.strip("/") else ""
    return base + "/" + "/".join(parts)


def default_blueprint(root: str = "/") -> rrb.Blueprint:
    """The default layout: the world on the left, the plots in a column on the right.

    Parameters
    ----------
    root : str
        The ``root`` the :class:`ScanLogger` instances were given.

    Returns
    -------
    rerun.blueprint.Blueprint
        ``Horizontal(3D "world" | Vertical(energy, ratio R, waveforms,
        Horizontal(sorted errors a | sorted errors b), events))`` with the
        world taking 3/5 of the width, the blueprint and selection panels
        collapsed and the ``step`` timeline active.
    """

    def at(*parts: str) -> str:
        return join_path(root, *parts)

    # Units in the titles (a Rerun plot has no axis labels); x is the step number on the default timeline.
    # The error charts' legend would show whole entity paths: the bars take their method's colour, as
    # the planes in 3D do.
    column = rrb.Vertical(
        rrb.TimeSeriesView(
            name="energy E^γ and E0(d_m), V²·s (x: step)",
            origin=at("plots", "energy"),
            plot_legend=rrb.PlotLegend("LeftTop"),
        ),
        rrb.TimeSeriesView(
            name="ratio R = E^γ / E0(d_m), no unit; ◆ critical step (x: step)",
            origin=at("plots", "ratio"),
            plot_legend=rrb.PlotLegend("LeftTop"),
        ),
        rrb.Spatial2DView(
            name="waveforms of the step: x ms after the ping, y V (capsule i at i·spacing)",
            origin=at("plots", "waveforms"),
        ),
        rrb.Horizontal(
            rrb.BarChartView(
                name="plane a: sorted errors e_i, m (colour = method)",
                origin=at("plots", "errors", "a"),
                plot_legend=rrb.PlotLegend(visible=False),
            ),
            rrb.BarChartView(
                name="plane b: sorted errors e_i, m (colour = method)",
                origin=at("plots", "errors", "b"),
                plot_legend=rrb.PlotLegend(visible=False),
            ),
        ),
        rrb.TextLogView(name="events", origin=at("log")),
        row_shares=[1.0, 1.0, 1.0, 1.0, 0.8],
    )
    return rrb.Blueprint(
        rrb.Horizontal(rrb.Spatial3DView(name="world", origin=at("world")), column, column_shares=[3.0, 2.0]),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(timeline=STEP_TIMELINE),
        auto_views=False,
    )
