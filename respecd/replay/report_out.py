"""Write the replay report: JSON (one entry per policy), a PNG timeline beside it, and the
comparison table printed after every replay.

Replaying the same log under another ``--policy`` into the same ``--report`` file adds that
policy's entry, so ``static`` / ``heuristic`` / ``exploit`` line up in one table and one
figure. A report for a different log is replaced, not merged.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import structlog

from respecd.atomicfile import write_atomically

log = structlog.get_logger(__name__)

COLUMNS = (
    ("policy", "policy", "{}"),
    ("F1", ("quality", "f1"), "{:.3f}"),
    ("recall", ("quality", "recall"), "{:.3f}"),
    ("precision", ("quality", "precision"), "{:.3f}"),
    ("ConfAgg", ("quality", "mean_conf_agg"), "{:.3f}"),
    ("infer ms/s", ("timing", "inference_ms_per_s"), "{:.0f}"),  # measured here, not the robot's
    ("Mpix/s", ("compute", "pixels_per_s"), "{:.2f}", 1e-6),
    ("sensor W", ("energy", "mean_w"), "{:.2f}"),
    ("switches", ("actions", "switches"), "{}"),
    ("decisions", "n_decisions", "{}"),
)


def merge(path: Path, log_id: dict[str, Any], policy: str, entry: dict[str, Any]) -> dict[str, Any]:
    """The report at ``path`` with ``entry`` added under ``policy`` (same log only)."""
    report: dict[str, Any] = {"log": log_id, "policies": {}}
    if path.is_file():
        try:
            old = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, ValueError) as err:
            log.warning("report.unreadable", path=str(path), error=str(err))
            old = None
        if isinstance(old, dict) and old.get("log") == log_id:
            report["policies"] = dict(old.get("policies") or {})
        elif old is not None:
            log.warning("report.replaced", path=str(path), reason="it describes another log")
    report["policies"][policy] = entry
    return report


def write(path: Path, report: dict[str, Any], figure: bool = True) -> Path | None:
    """Atomically write the JSON, then (``figure``) the PNG timeline next to it; returns the
    PNG path, or None without one (or without matplotlib, the ``lab`` extra: the JSON is the report)."""
    write_atomically(path, json.dumps(report, indent=1).encode("utf-8"))
    if not figure:
        return None
    plt = _pyplot()
    if plt is None:
        log.info("replay.report.no_png", reason="matplotlib not installed (pip install respecd[lab])")
        return None
    from respecd.replay.figure import plot

    png = path.with_suffix(".png")
    plot(report, png, plt)
    return png


def _pyplot() -> Any:
    """matplotlib's pyplot on the file-only Agg backend, or None without the lab extra."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return None
    return plt


def _cell(entry: dict[str, Any], policy: str, key: Any, fmt: str, scale: float = 1.0) -> str:
    if key == "policy":
        return policy
    if key == "n_decisions":
        return str(len(entry.get("decisions", [])))
    value = (entry.get(key[0]) or {}).get(key[1])
    if value is None:  # nothing to score against (no ground truth), a timing not measured, or an old entry
        return "-"
    return fmt.format(value * scale if scale != 1.0 else value)


def table(report: dict[str, Any]) -> str:
    """One row per policy: quality, compute, energy, switching."""
    rows = [[c[0] for c in COLUMNS]]
    for policy, entry in report["policies"].items():
        rows.append([_cell(entry, policy, c[1], c[2], *c[3:]) for c in COLUMNS])
    widths = [max(len(r[i]) for r in rows) for i in range(len(COLUMNS))]
    lines = ["  ".join(cell.rjust(w) if i else cell.ljust(w) for i, (cell, w) in enumerate(zip(r, widths, strict=True)))
             for r in rows]
    reference = {e["reference"] for e in report["policies"].values()}
    if reference == {"none"}:
        lines.append("no ground truth: the log has neither ground-truth boxes nor recorded detections, so F1, "
                     "recall and precision are not computed")
    else:
        lines.append(f"reference: {', '.join(sorted(reference))}; quality matched at IoU >= 0.5")
    lines += _detector_lines(report)
    for policy, entry in report["policies"].items():
        if entry.get("table") in ("no table",):
            lines.append(f"{policy}: no table (--allow-no-table): it held the start configuration")
        for sensor, short in (entry.get("unserved") or {}).items():
            lines.append(f"{policy}: {sensor} asked up to {short['asked_hz']:g} Hz {short['requests']}x, the log "
                         f"recorded {short['recorded_hz']:g} Hz: served at that for {short['seconds']:.1f} s")
    return "\n".join(lines)


def _detector_lines(report: dict[str, Any]) -> list[str]:
    """Which checkpoint ran, on which device, and (for a foreign bag on the default) how to choose another."""
    lines = []
    for detector in {json.dumps(e["detector"], sort_keys=True) for e in report["policies"].values() if "detector" in e}:
        d = json.loads(detector)
        if d.get("enabled") is False:
            continue
        line = f"detector: {d['weights']}" + (f" ({d['checkpoint']})" if "checkpoint" in d else "")
        runtime = d.get("runtime", "torch")
        line += f" on {d['device']}" + (f" through {runtime}" if runtime != "torch" else "")
        asked = [f"{d[f'profile_{k}']}" for k in ("runtime", "device", "precision") if f"profile_{k}" in d]
        line += f", not the profile's {' '.join(asked)}" if asked else ""
        lines.append(f"{line}; chosen by {d['chosen_by']}")
        lines += [f"  {d[k]}" for k in ("note", "hint") if k in d]
    return lines
