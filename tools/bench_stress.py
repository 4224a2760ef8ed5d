"""``lelsonar bench estimators --stress all``: scans *outside* the bench families, run through the real CLI path.

The project is judged on scenes from an independent simulator, recorded in
our schema and replayed with ``lelsonar reconstruct --source X.mcap --json``.
This sweep draws scenes and rigs the seeded families of
:mod:`lelsonar.sim.scenes` never produce, alone and in combination:

=============  =================================================================
family         what is drawn
=============  =================================================================
``distance``   each wall at 0.3–3 m, independently (unequal)
``opening``    corner opening 70–110° (one wall rolled against the other)
``tilt``       the whole L rolled ±20°, each wall skewed ±12° (edge off x)
``roll``       the whole L rolled ±45° (a robot far from square to the corner)
``sweep``      narrow (corner ±12–30°) and asymmetric sweeps, half reversed
               (γ from high to low: ``ScanStart.direction`` DECREASING)
``steps``      60–400 steps, uniform, jittered or two densities
``array``      2–8 capsules, pitch 3–15 cm, uneven (±40 % of the pitch),
               radial offset 0–10 cm
``rate``       sample rate 100 kHz–1 MHz, INT16 or float32 waveforms, late t0
``noise``      range jitter 1–8 mm, slips 0–8 %, amplitude noise 0–10 %,
               receiver noise 2–12 mV
``corner``     corner (double-bounce) gain 0–3
``missing``    10–35 % of readings without an echo, scattered or in runs
``calib``      the announced ``E0(d)`` off by a factor 0.5–2 (another rig's)
``nocorner``   a sweep that sees only one wall (the corner is outside it)
``wire``       what the schema allows and our writer never does: capsules
               listed in another order (in ``ScanStart`` and every
               ``Sample``), samples written out of step order, reversed
``mixed``      all of the above at once (reversed half the time)
``extreme``    mixed, wider: walls 0.25–4 m, opening 60–120° with double
               bounces at any opening (a simulator without the 90° ±10°
               retro-reflection limit), ``E0`` off by 0.1–10, reversed half
               the time
``comparator`` a board whose comparator times the echo's threshold crossing
               (``Receiver.timing = "crossing"``: later on weaker echoes):
               threshold 0.02–0.15 V, envelope rise
               0.08–0.4 ms, echo gain 1–6 V·m, walls 0.6–2.5 m, the L rolled
               ±15°, half the sweeps narrow or asymmetric
=============  =================================================================

Each scan is simulated by the project's simulator physics
(:func:`lelsonar.sim.scan.echo_table` and the comparator, noise and
waveform stages of :func:`simulate_scan`), but on any schedule (order and
spacing), recorded by the acquisition scan loop and
:class:`lelsonar.log.recording.McapRecorder` exactly as ``lelsonar acquire``
writes it, and reconstructed by ``lelsonar reconstruct --source FILE --json``
(the CLI's ``main``, in process, stdout captured).

Every wall of the scene is judged against its ground truth (the scene's
panel) and the oracle (LS on the true mirror echoes, as
:mod:`lelsonar.tools.bench_families`):

* **accurate**: not a failure (patch error ≤ 2 cm or ≤ 3× the oracle's);
* **flagged**: a failure whose quality is not ``good`` (degraded/unreliable,
  with ``quality_reasons``), or no plane with a non-zero exit code;
* **claims good** (the bug): a failure whose quality is ``good``; also a
  ``good`` plane of a wall that was never observed (fewer than 3 mirror echoes);
* **crash**: the command raised, printed no JSON line, or exited with an
  undocumented code (documented: 0, 1 = no final or a method produced no
  plane, 2 = typed error).

Every plane's reported standard errors are judged too (principle 1: an honest
σ), for the method of record ``corner`` and the compared ``ls``
(``--compare ls``: the cross-check only degrades the compared planes, the
record's are unchanged): **z** = error / standard error for the normal (angle
/ ``normal_stderr``) and the offset (``(h − h_true)/offset_stderr``), as
:mod:`lelsonar.tools.bench_families` — median |z| ≈ 0.8 / 0.7 and ~0.3 %
beyond 3 when calibrated.  The z table gives, per family, the median |z| and
the share beyond 3 over the planes that claim ``good`` and over all planes of
observed walls.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from lelsonar.cli.executor import add_ray_argument, config_from_args, map_values
from lelsonar.tools.family_metrics import (
    frac_above,
    is_failure,
    json_default,
    ls_plane,
    percentile,
    plane_errors,
    z_score,
)
from lelsonar.tools.stress_cases import (
    COMPARED,
    DOCUMENTED_EXIT,
    FAMILIES,
    RECORD,
    VERDICTS,
    StressCase,
    StressScan,
    build_config,
    draw_case,
    energy_model,
    record,
    run_cli,
    simulate,
)

#: The cases are re-exported: the tests and the foreign scenes import them from here.
__all__ = [
    "COMPARED",
    "RECORD",
    "DOCUMENTED_EXIT",
    "FAMILIES",
    "StressCase",
    "StressScan",
    "VERDICTS",
    "add_stress_arguments",
    "build_config",
    "draw_case",
    "energy_model",
    "judge",
    "main",
    "record",
    "run_cli",
    "run_stress",
    "simulate",
    "stress_scan",
    "tally",
    "z_summary",
]


# ---------------------------------------------------------------------------- judging
def judge(scan: StressScan, code: int | None, lines: list[dict[str, Any]], error: str) -> list[dict[str, Any]]:
    """One row per wall: errors against the truth and the oracle, quality, verdict (see the module docstring)."""
    from lelsonar.sim.scan import EchoSource

    cfg = scan.config
    pc = cfg.geometry.capsule_positions(scan.gamma_measured)
    distance = cfg.sound_speed * scan.tof / 2.0
    rows = []
    crashed = code not in DOCUMENTED_EXIT or not lines
    # Consumers pick the plane of record by method name (a fallback plane carries that name too).
    all_planes = [p for msg in lines for p in msg.get("planes", [])]
    planes = [p for p in all_planes if p.get("method", RECORD) == RECORD]
    compared = [p for p in all_planes if p.get("method") == COMPARED]
    for label, src, panel in (
        ("a", EchoSource.PLANE_A, cfg.scene.panels[0]),
        ("b", EchoSource.PLANE_B, cfg.scene.panels[1]),
    ):
        n_true, h_true = np.asarray(panel.normal), panel.offset
        m = (scan.echo_source == src) & np.isfinite(distance)
        patch = pc[m] + (h_true - pc[m] @ n_true)[:, None] * n_true
        oracle = float("nan")
        if m.sum() >= 3:
            n_o, h_o, _, _ = ls_plane(pc[m] + distance[m][:, None] * n_true)
            oracle = plane_errors(n_o, h_o, n_true, h_true, patch)[2]
        row: dict[str, Any] = {
            "family": scan.case.family,
            "seed": scan.case.seed,
            "label": label,
            "reverse": scan.case.reverse,
            "n_mirror": int(m.sum()),
            "oracle_patch_cm": oracle,
            "exit": code,
        }
        fit = next((p for p in planes if p.get("label") == label), None)
        if crashed:
            row.update(verdict="crash", error=error.strip().splitlines()[-1:] if error else ["no JSON line"])
        elif fit is None:
            # No plane is an honest answer only with the documented non-zero exit.
            row.update(verdict="flagged" if code != 0 else "claims_good", quality=None)
        else:
            n = np.array([fit["normal"].get(k, 0.0) for k in ("x", "y", "z")])
            h = float(fit.get("offset", 0.0))
            quality = fit.get("quality")
            row.update(quality=quality, reasons=fit.get("quality_reasons", []))
            if m.sum() >= 3:
                ang, off, pe = plane_errors(n, h, n_true, h_true, patch)
                row.update(angle_deg=ang, offset_cm=off, patch_cm=pe, **_z_fields(fit, ang, off))
                wrong = is_failure(pe, oracle)
            else:  # never observed: any plane is a guess
                wrong = True
            row["verdict"] = "accurate" if not wrong else ("claims_good" if quality == "good" else "flagged")
        other = next((p for p in compared if p.get("label") == label), None)
        if not crashed and other is not None and m.sum() >= 3:
            n = np.array([other["normal"].get(k, 0.0) for k in ("x", "y", "z")])
            ang, off, pe = plane_errors(n, float(other.get("offset", 0.0)), n_true, h_true, patch)
            row.update(
                {f"{COMPARED}_{k}": v for k, v in _z_fields(other, ang, off).items()},
                **{f"{COMPARED}_quality": other.get("quality"), f"{COMPARED}_patch_cm": pe},
            )
        rows.append(row)
    return rows


def _z_fields(plane: dict[str, Any], angle_deg: float, offset_cm: float) -> dict[str, float]:
    """A JSON plane's standard errors (°, cm) and z-scores of its angle (°) and offset (cm) errors."""
    se_n = float(plane.get("normal_stderr", float("nan")))
    se_h = float(plane.get("offset_stderr", float("nan")))
    return {
        "normal_stderr_deg": math.degrees(se_n),
        "offset_stderr_cm": 100.0 * se_h,
        "z_angle": z_score(math.radians(angle_deg), se_n),
        "z_offset": z_score(offset_cm / 100.0, se_h),
    }


def stress_scan(family: str, seed: int, keep_dir: str | None = None) -> list[dict[str, Any]]:
    """Draw, simulate, record, reconstruct through the CLI and judge one case; rows per wall."""
    from lelsonar.errors import ConfigError, PayloadTooLargeError

    try:
        case = draw_case(family, seed)
        scan = simulate(case)
    except (ValueError, ConfigError) as exc:  # an impossible scene is the sweep's problem, not the estimator's
        return [{"family": family, "seed": seed, "label": "-", "verdict": "skipped", "error": str(exc)}]
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(keep_dir or tmp) / f"{family}-{seed}.mcap"
        path.parent.mkdir(parents=True, exist_ok=True)
        try:
            record(scan, path)
        except PayloadTooLargeError as exc:  # the recorder refuses it (e.g. a window over the codec's limit)
            return [{"family": family, "seed": seed, "label": "-", "verdict": "skipped", "error": str(exc)}]
        code, lines, error = run_cli(path)
        rows = judge(scan, code, lines, error)
        if keep_dir and not any(r["verdict"] in ("claims_good", "crash") for r in rows):
            path.unlink()
    for r in rows:
        r["case"] = case.describe()
    return rows


def tally(rows: list[dict[str, Any]]) -> dict[str, dict[str, int]]:
    """Per family (and ``all``): planes and the count of each verdict."""
    out: dict[str, dict[str, int]] = {}
    for r in rows:
        if r["verdict"] == "skipped":
            continue
        for key in (r["family"], "all"):
            t = out.setdefault(key, {"planes": 0, "unseen": 0, **{v: 0 for v in VERDICTS}})
            t["planes"] += 1
            t["unseen"] += int(r.get("n_mirror", 0) < 3)
            t[r["verdict"]] += 1
    return out


def z_summary(rows: list[dict[str, Any]], prefix: str = "") -> dict[str, dict[str, float]]:
    """Per family (and ``all``): the z-scores of one method's planes (``prefix`` ``""`` record, ``"ls_"`` compared).

    For ``good`` (planes claiming good) and ``all`` (every plane of an observed wall): ``n``, median |z| and
    the share of |z| > 3, of the normal (``zn``) and the offset (``zh``).
    """

    def num(r: dict[str, Any], key: str) -> float:
        v = r.get(prefix + key)
        return float(v) if v is not None else float("nan")

    out: dict[str, dict[str, float]] = {}
    for fam in {r["family"] for r in rows} | {"all"}:
        fr = [r for r in rows if (fam == "all" or r["family"] == fam) and math.isfinite(num(r, "z_angle"))]
        stats: dict[str, float] = {}
        for which, sel in (("good", [r for r in fr if r.get(prefix + "quality") == "good"]), ("all", fr)):
            zn = np.abs([num(r, "z_angle") for r in sel], dtype=float)
            zh = np.abs([num(r, "z_offset") for r in sel], dtype=float)
            stats.update(
                {
                    f"{which}_n": len(sel),
                    f"{which}_zn_med": percentile(zn, 50),
                    f"{which}_zn_gt3": frac_above(zn, 3.0),
                    f"{which}_zh_med": percentile(zh, 50),
                    f"{which}_zh_gt3": frac_above(zh, 3.0),
                }
            )
        out[fam] = stats
    return out


def _z_cell(s: dict[str, float], which: str, z: str) -> str:
    med, gt3 = s.get(f"{which}_{z}_med", float("nan")), s.get(f"{which}_{z}_gt3", float("nan"))
    if not math.isfinite(med):
        return "–"
    return f"{med:.2f}, {100 * gt3:.0f} %"


def run_stress(args: argparse.Namespace) -> int:
    """Run the sweep; print the table and the bugs; exit 1 if any wall claims good while wrong or a scan crashed."""
    from rich.console import Console
    from rich.table import Table

    families = FAMILIES if "all" in args.stress else tuple(args.stress)
    for f in families:
        if f not in FAMILIES:
            raise SystemExit(f"unknown stress family {f!r}; choose from all, {', '.join(FAMILIES)}")
    jobs = [(f, s) for f in families for s in range(args.first_seed, args.first_seed + args.seeds)]
    rows: list[dict[str, Any]] = []
    items = [(f, s, args.keep) for f, s in jobs]
    for res in map_values(stress_scan, items, config_from_args(args, "jobs")):
        rows.extend(res)
    console = Console(width=max(Console().width, 160))
    table = Table(title=f"stress sweep: {args.seeds} seeds from {args.first_seed}, method corner")
    for col in ("family", "planes", "unseen", *VERDICTS):
        table.add_column(col, justify="right" if col != "family" else "left")
    counts = tally(rows)
    for fam in (*families, "all"):
        if fam in counts:
            t = counts[fam]
            table.add_row(fam, str(t["planes"]), str(t["unseen"]), *(str(t[v]) for v in VERDICTS))
    console.print(table)
    console.print(
        "planes: walls of the scenes; unseen: walls with fewer than 3 true mirror echoes (no plane, or a "
        "flagged one, is the right answer); accurate: patch error ≤ 2 cm or ≤ 3× the oracle's; flagged: "
        "a failure whose quality is not good, or no plane with a non-zero exit; claims_good: a failure "
        "(or a plane of an unseen wall) whose quality is good; crash: an exception, no JSON line or an "
        "undocumented exit code"
    )
    zs = {m: z_summary(rows, prefix) for m, prefix in ((RECORD, ""), (COMPARED, COMPARED + "_"))}
    zt = Table(title="honest σ: |z| = |error| / reported standard error (median, share > 3), normal and offset")
    for col in ("family", "method", "good", "|z_n| good", "|z_h| good", "all", "|z_n| all", "|z_h| all"):
        zt.add_column(col, justify="right" if col not in ("family", "method") else "left")
    for fam in (*families, "all"):
        for m in (RECORD, COMPARED):
            s = zs[m].get(fam)
            if s:
                zt.add_row(
                    fam,
                    m,
                    str(s["good_n"]),
                    _z_cell(s, "good", "zn"),
                    _z_cell(s, "good", "zh"),
                    str(s["all_n"]),
                    _z_cell(s, "all", "zn"),
                    _z_cell(s, "all", "zh"),
                )
        zt.add_section()
    console.print(zt)
    console.print(
        "calibrated: median |z| ≈ 0.8 (normal, a 2-D tilt) / 0.7 (offset) and ~0.3 % beyond 3; "
        f"{COMPARED}'s quality is after the cross-check against the method of record"
    )
    bad = [r for r in rows if r["verdict"] in ("claims_good", "crash")]
    for r in bad:
        console.print(
            f"[red]{r['verdict']}[/] {r['case']} plane {r['label']}: "
            f"patch {r.get('patch_cm', float('nan')):.2f} cm (oracle {r.get('oracle_patch_cm', float('nan')):.2f}), "
            f"mirror echoes {r.get('n_mirror')}, exit {r.get('exit')} {r.get('error', '')}",
            highlight=False,
        )
    skipped = [r for r in rows if r["verdict"] == "skipped"]
    if skipped:
        console.print(f"{len(skipped)} draws skipped (invalid configuration): {skipped[0]['error']}")
    if args.json:
        Path(args.json).write_text(
            json.dumps({"rows": rows, "tally": counts, "z": zs}, default=json_default, indent=None), encoding="utf-8"
        )
    return 1 if bad else 0


def add_stress_arguments(parser: argparse.ArgumentParser) -> None:
    """``--stress FAMILY…`` (with ``--seeds``, ``--first-seed``, ``--jobs``, ``--json`` shared)."""
    g = parser.add_argument_group("stress sweep (scenes outside the families, through reconstruct --source)")
    g.add_argument(
        "--stress", nargs="+", metavar="NAME", help=f"run the stress sweep: 'all' or names from {', '.join(FAMILIES)}"
    )
    g.add_argument(
        "--keep",
        metavar="DIR",
        help="with --stress: keep the recordings of scans with a bug (crash, claims good) in DIR",
    )


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="bench_stress", description=__doc__.splitlines()[0])
    p.add_argument("--seeds", type=int, default=10)
    p.add_argument("--first-seed", type=int, default=0)
    p.add_argument("--jobs", type=int, default=os.cpu_count() or 1)
    p.add_argument("--json")
    add_ray_argument(p)
    add_stress_arguments(p)
    args = p.parse_args(argv)
    if not args.stress:
        args.stress = ["all"]
    return run_stress(args)


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
