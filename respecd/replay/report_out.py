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
from respecd.messages import MODALITIES

log = structlog.get_logger(__name__)

COLUMNS = (
    ("policy", "policy", "{}"),
    ("F1", ("quality", "f1"), "{:.3f}"),
    ("recall", ("quality", "recall"), "{:.3f}"),
    ("precision", ("quality", "precision"), "{:.3f}"),
    ("ConfAgg", ("quality", "mean_conf_agg"), "{:.3f}"),
    ("infer ms/s", ("compute", "inference_ms_per_s"), "{:.0f}"),
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
    if value is None:  # nothing to score against (no ground truth), or a figure not measured
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
    return "\n".join(lines)


def _detector_lines(report: dict[str, Any]) -> list[str]:
    """Which checkpoint ran, on which device, and (for a foreign bag on the default) how to choose another."""
    lines = []
    for detector in {json.dumps(e["detector"], sort_keys=True) for e in report["policies"].values() if "detector" in e}:
        d = json.loads(detector)
        if d.get("enabled") is False:
            continue
        line = f"detector: {d['weights']}" + (f" ({d['checkpoint']})" if "checkpoint" in d else "")
        line += f" on {d['device']}" + (f", not the profile's {d['profile_device']}" if "profile_device" in d else "")
        lines.append(f"{line}; chosen by {d['chosen_by']}")
        lines += [f"  {d[k]}" for k in ("note", "hint") if k in d]
    return lines


def plot(report: dict[str, Any], png: Path, plt: Any) -> None:
    """Timeline per policy: actions, contributions, ConfAgg, latency (the load signal)."""
    names: dict[str, int] = {}
    for entry in report["policies"].values():  # the action labels first: they size the left margin
        for d in entry["decisions"]:
            names.setdefault(_action_label(d), len(names))
    fig, axes = plt.subplots(4, 1, figsize=(12, 4.5 + 5.5 + 0.18 * len(names)), sharex=True,
                             gridspec_kw={"height_ratios": [1.2 + 0.12 * len(names), 1, 1, 1]})
    for policy, entry in report["policies"].items():
        _plot_actions(axes[0], policy, entry, names)
        times = [p["t"] for p in entry["timeline"]]
        axes[2].plot(times, [p["conf_agg"] for p in entry["timeline"]], label=policy, lw=1)
        axes[3].plot(times, [p["latency_ms"] for p in entry["timeline"]], label=policy, lw=1)
        contributions = [(p["t"], p["contributions"]) for p in entry["timeline"] if p["contributions"]]
        keys = {m for _, c in contributions for m in c}
        modalities = keys & set(MODALITIES) or keys  # per-modality scores, not per input channel
        for modality in sorted(modalities):
            axes[1].plot([t for t, _ in contributions], [c.get(modality, 0.0) for _, c in contributions],
                         label=f"{policy}: {modality}", lw=1, marker=".", ms=3)
    titles = ("action chosen at each decision", "contribution per modality", "ConfAgg", "perception latency")
    ylabels = ("action", "contribution (0-1)", "ConfAgg (0-1)", "latency (ms)")
    for ax, title, ylabel in zip(axes, titles, ylabels, strict=True):
        ax.set_title(title, fontsize=9, loc="left")
        ax.set_ylabel(ylabel, fontsize=8)
        ax.grid(alpha=0.3)
        if ax.lines:  # outside the axes, to the right: never over the data
            ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0)
    axes[-1].set_xlabel("log time (s)")
    fig.suptitle(f"replay of {Path(report['log']['path']).name}: actions, contributions, ConfAgg, latency per policy",
                 fontsize=10)
    fig.tight_layout()
    fig.savefig(png, dpi=90, bbox_inches="tight")  # keeps the full action labels and the outside legends
    plt.close(fig)


def _action_label(decision: dict[str, Any]) -> str:
    """The whole action name, one sensor setting per line (rgb 960x540@10Hz / thermal ... )."""
    name = str(decision.get("action_name") or decision["action"])
    parts = name.split(" ")
    return "\n".join(" ".join(parts[i : i + 2]) for i in range(0, len(parts), 2))


def _plot_actions(ax: Any, policy: str, entry: dict[str, Any], names: dict[str, int]) -> None:
    """Action chosen at each decision, one step line per policy; y ticks name the actions."""
    decisions = entry["decisions"]
    if not decisions:
        return
    ys = [names.setdefault(_action_label(d), len(names)) for d in decisions]
    ax.step([d["t"] for d in decisions], ys, where="post", label=policy, lw=1, marker=".", ms=4)
    ax.set_yticks(range(len(names)), list(names), fontsize=6.5)
