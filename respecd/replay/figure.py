"""The replay report's PNG timeline: per policy, what each sensor ran, the contribution per
modality, ConfAgg and perception latency, on one log-time axis.

The action panel has one lane per policy and sensor: a bar per stretch of one applied setting
(``960x540@5Hz``, ``range@10Hz``, ``off``), labelled where the label fits. A lane per sensor
stays readable however many distinct actions a policy took (a learning policy over the
rover's 1,296 actions named each one on a y tick of its own before, and the names overlapped).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from respecd.messages import MODALITIES

LABEL_PT = 7.0
CHAR_WIDTH_EM = 0.6  # a character of the default sans-serif at LABEL_PT, in ems (what fits a bar)
WIDTH_IN = 12.0
DPI = 90


def plot(report: dict[str, Any], png: Path, plt: Any) -> None:
    """Timeline per policy: sensor settings, contributions, ConfAgg, latency (the load signal)."""
    policies = report["policies"]
    lanes = [(policy, sensor) for policy, entry in policies.items() for sensor in _sensors(entry)]
    fig, axes = plt.subplots(4, 1, figsize=(WIDTH_IN, 8.0 + 0.28 * len(lanes)), sharex=True,
                             gridspec_kw={"height_ratios": [0.6 + 0.1 * len(lanes), 1, 1, 1]})
    span = _span(policies)
    for row, (policy, sensor) in enumerate(lanes):
        _lane(plt, axes[0], row, policies[policy], sensor, span, _bar_width_in(fig, axes[0]) / (span[1] - span[0]))
    axes[0].set_yticks(range(len(lanes)), [f"{p}: {s}" if len(policies) > 1 else s for p, s in lanes], fontsize=8)
    axes[0].set_ylim(len(lanes) - 0.5, -0.5)  # first lane on top
    for policy, entry in policies.items():
        _plot_signals(axes, policy, entry)
    titles = ("sensor settings the policy's actions applied (one lane per sensor)", "contribution per modality",
              "ConfAgg", "perception latency")
    ylabels = ("", "contribution (0-1)", "ConfAgg (0-1)", "latency (ms)")
    for ax, title, ylabel in zip(axes, titles, ylabels, strict=True):
        ax.set_title(title, fontsize=9, loc="left")
        ax.set_ylabel(ylabel, fontsize=8)
        ax.grid(alpha=0.3, axis="x" if ax is axes[0] else "both")
        if ax.lines:  # outside the axes, to the right: never over the data
            ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0)
    axes[-1].set_xlim(*span)
    axes[-1].set_xlabel("log time (s)")
    fig.suptitle(f"replay of {Path(report['log']['path']).name}: sensor settings, contributions, ConfAgg, "
                 "latency per policy", fontsize=10)
    fig.tight_layout()
    fig.savefig(png, dpi=DPI, bbox_inches="tight")
    plt.close(fig)


def _sensors(entry: dict[str, Any]) -> list[str]:
    """The sensors with an applied configuration, in the order the report lists them."""
    return list(dict.fromkeys(c["sensor"] for c in entry.get("configs", [])))


def _span(policies: dict[str, Any]) -> tuple[float, float]:
    """Log time from the first applied configuration to the end of the longest replay."""
    starts = [c["t"] for e in policies.values() for c in e.get("configs", [])]
    starts += [p["t"] for e in policies.values() for p in e.get("timeline", [])]
    t0 = min(starts, default=0.0)
    t1 = t0 + max((float(e.get("replayed_s", 0.0)) for e in policies.values()), default=0.0)
    return t0, max(t1, t0 + 1e-3)


def _setting(config: dict[str, Any]) -> str:
    if not config.get("enabled", True):
        return "off"
    rate = f"{config['rate_hz']:g}Hz"
    return f"{config['setting']}@{rate}" if config.get("setting") else rate


def _stretches(entry: dict[str, Any], sensor: str, end: float) -> list[tuple[float, float, str]]:
    """(start, end, setting) of each stretch one setting ran, merged where nothing changed."""
    changes = [(c["t"], _setting(c)) for c in entry.get("configs", []) if c["sensor"] == sensor]
    stretches: list[tuple[float, float, str]] = []
    for i, (t, label) in enumerate(changes):
        stop = changes[i + 1][0] if i + 1 < len(changes) else end
        if stretches and stretches[-1][2] == label:
            stretches[-1] = (stretches[-1][0], stop, label)
        elif stop > t:
            stretches.append((t, stop, label))
    return stretches


def _lane(plt: Any, ax: Any, row: int, entry: dict[str, Any], sensor: str, span: tuple[float, float],
          inches_per_s: float) -> None:
    """One sensor's settings as bars, one colour per setting, labelled where the label fits."""
    palette = [plt.colormaps[name](i) for name, n in (("Pastel1", 9), ("Pastel2", 8)) for i in range(n)]  # 17 light
    colours: dict[str, Any] = {}
    for start, stop, label in _stretches(entry, sensor, span[1]):
        colour = colours.setdefault(label, palette[len(colours) % len(palette)])
        ax.broken_barh([(start, stop - start)], (row - 0.4, 0.8), facecolors=colour, edgecolors="0.45", lw=0.5)
        if (stop - start) * inches_per_s >= (len(label) + 1) * CHAR_WIDTH_EM * LABEL_PT / 72:
            ax.text((start + stop) / 2, row, label, ha="center", va="center", fontsize=LABEL_PT, clip_on=True)


def _bar_width_in(fig: Any, ax: Any) -> float:
    """The action panel's width in inches, once the layout has placed it."""
    fig.tight_layout()
    return float(ax.get_position().width * fig.get_figwidth())


def _plot_signals(axes: Any, policy: str, entry: dict[str, Any]) -> None:
    times = [p["t"] for p in entry["timeline"]]
    axes[2].plot(times, [p["conf_agg"] for p in entry["timeline"]], label=policy, lw=1, marker=".", ms=2)
    axes[3].plot(times, [p["latency_ms"] for p in entry["timeline"]], label=policy, lw=1, marker=".", ms=2)
    contributions = [(p["t"], p["contributions"]) for p in entry["timeline"] if p["contributions"]]
    keys = {m for _, c in contributions for m in c}
    modalities = keys & set(MODALITIES) or keys  # per-modality scores, not per input channel
    for modality in sorted(modalities):
        axes[1].plot([t for t, _ in contributions], [c.get(modality, 0.0) for _, c in contributions],
                     label=f"{policy}: {modality}", lw=1, marker=".", ms=3)
