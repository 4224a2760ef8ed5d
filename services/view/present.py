"""Estimates for people and scripts: rich tables and JSON lines (no I/O beyond returning text)."""

from __future__ import annotations

import copy
import json

import numpy as np
from google.protobuf.json_format import MessageToDict, ParseDict
from rich.console import Console
from rich.table import Table

from lelsonar import codec
from lelsonar.codec import QUALITY, QUALITY_NAME
from lelsonar.reconstruct.estimate.surfaces.features import placement_caveats
from lelsonar.reconstruct.estimate.wire import STATUS, accounting_text, status_name


class PipeConsole(Console):
    """A console whose closed pipe (``lelsonar info | head -1``) raises :class:`BrokenPipeError`, which the
    command line turns into exit code 141 as for plain prints (rich's own handling exits 1)."""

    def on_broken_pipe(self) -> None:
        self.quiet = True
        raise BrokenPipeError(32, "the reader closed the pipe")


def console(stderr: bool = False) -> Console:
    """A console that keeps tables readable when the output is a pipe or a CI log (no terminal width)."""
    c = PipeConsole(stderr=stderr)
    return c if c.is_terminal else PipeConsole(stderr=stderr, width=120)


#: Keys :func:`to_json` adds beside the message's own fields (read back by :func:`from_json` without them).
_SURFACE_KEYS = ("kind", "quality", "reasons")
_FEATURE_KEYS = ("kind",)
_UNEXPLAINED_KEYS = ("share",)
_TOP_KEYS = ("unexplained_share",)


def to_json(msg: codec.Reconstruction) -> str:
    """One JSON line: the message's fields (SI units) with proto field names.

    Beside them, for a reader of the surfaces: each surface's ``kind`` ("plane"), ``quality`` and
    ``reasons`` (its plane's verdict); each corner's and edge's ``kind`` ("corner", "edge"); each cause of
    unexplained echoes' ``share`` of the echoes the surfaces were extracted from, and their total
    ``unexplained_share`` (0 where the estimate carries no surfaces).
    """
    d = MessageToDict(msg, preserving_proto_field_name=True, always_print_fields_with_no_presence=True)
    d["status"] = status_name(msg)
    for plane, pd in zip(msg.planes, d.get("planes", [])):
        pd["quality"] = QUALITY_NAME.get(plane.quality, "unknown")
    for surface, sd in zip(msg.surfaces, d.get("surfaces", [])):
        quality = QUALITY_NAME.get(surface.plane.quality, "unknown")
        sd["plane"]["quality"] = quality
        sd.update(kind="plane", quality=quality, reasons=list(surface.plane.quality_reasons))
    for kind, features in (("corner", d.get("corners", [])), ("edge", d.get("edges", []))):
        for fd in features:
            fd["kind"] = kind
    n = msg.surface_echo_count
    for ud in d.get("unexplained", []):
        ud["share"] = int(ud.get("count", 0)) / n if n else 0.0
    d["unexplained_share"] = sum(u.count for u in msg.unexplained) / n if n else 0.0
    return json.dumps(d, separators=(",", ":"), sort_keys=True)


def from_json(line: str | dict) -> codec.Reconstruction:
    """The ``Reconstruction`` a :func:`to_json` line came from (short status and quality names mapped back,
    the keys it adds beside the message's fields left out).

    A dict given is left as it is (a copy is mapped back): the caller may compare it afterwards.
    """
    d = json.loads(line) if isinstance(line, str) else copy.deepcopy(dict(line))
    d["status"] = STATUS.get(str(d.get("status", "")), 0)
    for p in [*d.get("planes", []), *(sd.get("plane", {}) for sd in d.get("surfaces", []))]:
        p["quality"] = _quality_number(p.get("quality"))
    for items, keys in (
        ([d], _TOP_KEYS),
        (d.get("surfaces", []), _SURFACE_KEYS),
        ([*d.get("corners", []), *d.get("edges", [])], _FEATURE_KEYS),
        (d.get("unexplained", []), _UNEXPLAINED_KEYS),
    ):
        for item in items:
            for key in keys:
                item.pop(key, None)
    return ParseDict(d, codec.Reconstruction())


def _quality_number(name) -> int:
    return QUALITY.get("" if name == "unassessed" else name, 0)


def _vec(v) -> np.ndarray:
    return np.array([v.x, v.y, v.z])


def angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    """Angle between two unit normals, degrees."""
    return float(np.rad2deg(np.arccos(np.clip(abs(float(a @ b)), -1.0, 1.0))))


def planes_table(
    msg: codec.Reconstruction, truth: dict[str, tuple[np.ndarray, float]] | None = None, title: str | None = None
) -> Table:
    """One row per plane estimate; with ``truth`` (label → (normal, offset)), the errors in ° and cm."""
    crit = (
        f"critical step {msg.critical_step} at γ = {np.rad2deg(msg.critical_angle):.1f}°"
        if msg.HasField("critical_step")
        else "corner not found yet"
    )
    t = Table(
        title=title or f"{msg.scanner_id} scan {msg.scan_id} — {status_name(msg)}, {msg.samples_used} samples, {crit}",
        title_justify="left",
    )
    t.add_column("plane")
    t.add_column("method")
    t.add_column("normal n", no_wrap=True)
    t.add_column("h (cm)", justify="right")
    if truth:
        t.add_column("Δn (°)", justify="right")
        t.add_column("Δh (cm)", justify="right")
    for col in ("σ (mm)", "inliers", "H"):
        t.add_column(col, justify="right")
    t.add_column("quality")
    for p in sorted(msg.planes, key=lambda p: (p.label, p.method)):
        n = _vec(p.normal)
        cells = [p.label, p.method, f"{n[0]:+.3f} {n[1]:+.3f} {n[2]:+.3f}", f"{p.offset * 100:.2f}"]
        if truth:
            true_plane = truth.get(p.label)
            if true_plane is None:
                cells += ["", ""]
            else:
                tn, th = true_plane
                cells += [f"{angle_deg(n, tn):.2f}", f"{(p.offset - th) * 100:+.2f}"]
        cells += [f"{p.sigma * 1000:.1f}", f"{p.inlier_count}/{p.point_count}", f"{p.lel_cost:.3f}", quality_cell(p)]
        t.add_row(*cells)
    if truth:
        for label, (tn, th) in sorted(truth.items()):
            t.add_row(
                label,
                "truth",
                f"{tn[0]:+.3f} {tn[1]:+.3f} {tn[2]:+.3f}",
                f"{th * 100:.2f}",
                "",
                "",
                "",
                "",
                "",
                "",
                style="dim",
            )
    for f in msg.failures:
        t.add_row("", "failure", f, *[""] * (len(t.columns) - 3), style="yellow")
    caption = [
        f"* {p.label} {p.method}: {'; '.join(p.quality_reasons)}"
        for p in sorted(msg.planes, key=lambda p: (p.label, p.method))
        if p.quality_reasons
    ]
    if msg.HasField("accounting"):
        caption.append(
            f"samples: {accounting_text(msg.accounting)}"
            + (f"; missing steps {_runs(msg.missing_steps)}" if msg.missing_steps else "")
        )
        if msg.missing_steps:
            t.caption_style = "yellow"
    if caption:
        t.caption = "\n".join(caption)
        t.caption_justify = "left"
    return t


def surfaces_table(msg: codec.Reconstruction) -> Table | None:
    """Every surface of the sweep, one row each (bearing and tilt in °, offset in cm, their σ), then its
    corners and edges, and the echoes none of them explains (their causes and shares); None if the estimate
    carries no surfaces (a provisional one, or one made before surfaces were extracted)."""
    if not (msg.surfaces or msg.corners or msg.edges or msg.surface_echo_count):
        return None
    t = Table(
        title=f"{msg.scanner_id} scan {msg.scan_id} — every surface of the sweep ({msg.surface_echo_count} echoes)",
        title_justify="left",
    )
    for col, justify in (
        ("label", "left"),
        ("kind", "left"),
        ("bearing (°)", "right"),
        ("tilt (°)", "right"),
        ("h (cm)", "right"),
        ("echoes", "right"),
        ("quality", "left"),
        ("joins / bearing from", "left"),
    ):
        t.add_column(col, justify=justify)  # type: ignore[arg-type]
    for sf in msg.surfaces:
        cov = np.asarray(sf.covariance).reshape(3, 3) if len(sf.covariance) == 9 else np.full((3, 3), np.nan)
        sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
        plus = [f" ± {v:.2f}" if np.isfinite(v) else "" for v in (*np.rad2deg(sd[:2]), sd[2] * 100)]
        t.add_row(
            sf.label,
            "plane",
            f"{np.rad2deg(sf.bearing):+.2f}{plus[0]}",
            f"{np.rad2deg(sf.tilt):+.2f}{plus[1]}",
            f"{sf.plane.offset * 100:.2f}{plus[2]}",
            str(sf.echo_count),
            quality_cell(sf.plane),
            sf.bearing_source,
        )
    for kind, features in (("corner", msg.corners), ("edge", msg.edges)):
        for f in features:
            p = _vec(f.line.point)
            t.add_row(
                f.label,
                kind,
                f"{np.rad2deg(np.arctan2(p[2], p[1])):+.2f}",
                "",
                f"{np.linalg.norm(p[1:]) * 100:.2f} ± {f.line.point_stderr * 100:.2f}",
                str(f.echo_count),
                "",
                ", ".join(f.surfaces),
            )
    caption = [
        f"* {sf.label}: {'; '.join(sf.plane.quality_reasons)}" for sf in msg.surfaces if sf.plane.quality_reasons
    ]
    # A corner or an edge placed without a bearing of its own, or off the line its class names, says so beside its σ.
    for f in (*msg.corners, *msg.edges):
        caveats = placement_caveats(f.reasons)
        if caveats:
            caption.append(f"* {f.label}: {'; '.join(caveats)}")
    n = max(msg.surface_echo_count, 1)
    caption += [f"unexplained: {u.count} echoes ({100 * u.count / n:.1f} %) {u.cause}" for u in msg.unexplained]
    if caption:
        t.caption = "\n".join(caption)
        t.caption_justify = "left"
    return t


_QUALITY_STYLE = {"good": "green", "degraded": "yellow", "unreliable": "bold red"}


def quality_cell(plane) -> str:
    """The verdict, coloured (rich markup); its reasons follow the table (:func:`planes_table`)."""
    name = QUALITY_NAME.get(plane.quality, "unknown")
    return f"[{_QUALITY_STYLE.get(name, 'dim')}]{name}[/]" + ("*" if plane.quality_reasons else "")


def _runs(steps) -> str:
    out: list[list[int]] = []
    for s in steps:
        if out and s == out[-1][1] + 1:
            out[-1][1] = s
        else:
            out.append([s, s])
    text = ", ".join(str(a) if a == b else f"{a}-{b}" for a, b in out[:20])
    return text + (f", … ({len(out) - 20} more runs)" if len(out) > 20 else "")


def plane_equations(msg: codec.Reconstruction, method: str) -> list[str]:
    """The paper's way of writing a plane (eq. 16–19, cm): ``y = a x + b z + c`` for a, ``z = a x + b y + c`` for b."""
    out = []
    for p in msg.planes:
        if p.method != method:
            continue
        n, h = _vec(p.normal), p.offset * 100
        if p.label == "a" and abs(n[1]) > 1e-9:
            out.append(f"y = {-n[0] / n[1]:+.6f}x {-n[2] / n[1]:+.6f}z {h / n[1]:+.4f}")
        elif p.label == "b" and abs(n[2]) > 1e-9:
            out.append(f"z = {-n[0] / n[2]:+.6f}x {-n[1] / n[2]:+.6f}y {h / n[2]:+.4f}")
    return out
