"""The comparison as a Markdown table and as a figure in the spirit of the paper's: per
scenario, the chosen setting and rate of each modality, then accuracy and load, for the
three policies side by side."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

POLICY_COLORS = {"static": "#8c8c8c", "heuristic": "#d9a03f", "rl": "#2f6db3", "old-heuristic": "#e8d3a6"}
POLICY_ORDER = ("static", "old-heuristic", "heuristic", "rl")
MODALITY_ROWS = (("rgb", "RGB rate (Hz)"), ("thermal", "thermal rate (Hz)"), ("radar", "radar rate (Hz)"),
                 ("depth", "depth rate (Hz)"))


def number(value: Any, spec: str) -> str:
    return "n/a" if value is None else format(value, spec)


def reduction_text(reduction: float | None) -> str:
    return "n/a" if reduction is None else f"{abs(100 * reduction):.1f} % {'less' if reduction >= 0 else 'more'}"


def drop_text(drop: float | None) -> str:
    return "n/a" if drop is None else f"{abs(drop):.3f} {'lower' if drop >= 0 else 'higher'}"


def _range(values: list[Any] | None, spec: str, scale: float = 1.0) -> str:
    if not values or values[0] is None:
        return "n/a"
    return f"{values[0] / scale:{spec}}–{values[1] / scale:{spec}}"


def markdown(result: dict[str, Any]) -> str:
    """The per-scenario table (pooled over the world sets), the pooled figures with their
    spread over the sets, what each scenario's mAP rests on, and the summary."""
    stats = result.get("statistics", {}).get("scenarios", {})
    lines = ["| scenario | policy | stabilized action | mAP@0.5 | ± (SE) | accelerator load | compute ms/s | "
             "energy J | bandwidth MB/s | read MB/s |", "|---|---|---|---:|---:|---:|---:|---:|---:|---:|"]
    for row in result["scenarios"]:
        se = stats.get(row["scenario"], {}).get(row["policy"], {}).get("map50_se")
        lines.append(f"| {row['scenario']} | {row['policy']} | {row['action']} | {number(row['map50'], '.3f')} | "
                     f"{number(se, '.3f')} | {row['accelerator_load']:.3f} | {row['compute_ms_per_s']:.0f} | "
                     f"{row['energy_j']:.1f} | {row['bandwidth_bps'] / 1e6:.2f} | "
                     f"{row['bandwidth_read_bps'] / 1e6:.2f} |")
    lines += ["", pooled_table(result)]
    if stats:
        lines += ["", "| scenario | worlds | people | scored instants | targets |", "|---|---:|---:|---:|---:|"]
        for name, c in stats.items():
            lines.append(f"| {name} | {c['worlds']} | {number(c['people'], 'd')} | {c['instants']} | {c['targets']} |")
    lines.append("")
    lines += [f"- {line}" for line in headline(result)]
    lines += ["", "| goal | measured | met? |", "|---|---:|---|"]
    for g in goals(result):
        met = "n/a" if g["met"] is None else ("yes" if g["met"] else "**no**")
        lines.append(f"| {g['goal']} | {number(g['measured'], '+.3f')} | {met} |")
    return "\n".join(lines) + "\n"


def pooled_table(result: dict[str, Any]) -> str:
    """Per policy: pooled mAP@0.5, accelerator load, compute asked for, energy, bandwidth (all and read),
    with the [min, max] over world sets."""
    spread = result.get("spread", {})
    lines = ["| policy (pooled) | mAP@0.5 | over sets | accelerator load | over sets | compute ms/s | energy J "
             "(accelerator) | bandwidth MB/s | read MB/s | over sets |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for policy, v in result.get("pooled", {}).items():
        s = spread.get(policy, {})
        lines.append(f"| {policy} | {number(v['map50'], '.3f')} | {_range(s.get('map50'), '.3f')} | "
                     f"{v['accelerator_load']:.3f} | {_range(s.get('accelerator_load'), '.3f')} | "
                     f"{v['compute_ms_per_s']:.0f} | {v['energy_j']:.1f} ({v['accelerator_j']:.1f}) | "
                     f"{v['bandwidth_bps'] / 1e6:.2f} | {v['bandwidth_read_bps'] / 1e6:.2f} | "
                     f"{_range(s.get('bandwidth_read_bps'), '.2f', 1e6)} |")
    return "\n".join(lines)


# The headline's targets (issue 48): (name, summary entry, key, bound, at least?)
GOALS = (
    ("static is the accuracy ceiling: static mAP@0.5 ≥ every other policy's − 0.02", None, None, -0.02, True),
    ("RL vs static: accelerator load ≥ 40 % less", "rl_vs_static", "load_reduction", 0.40, True),
    ("RL vs static: mAP@0.5 ≤ 0.03 lower", "rl_vs_static", "map50_drop", 0.03, False),
    ("RL vs heuristic: accelerator load ≥ 25 % less", "rl_vs_heuristic", "load_reduction", 0.25, True),
    ("RL vs heuristic: read-sensor bandwidth ≥ 25 % less", "rl_vs_heuristic", "bandwidth_read_reduction", 0.25, True),
    ("RL vs heuristic: mAP@0.5 ≤ 0.01 lower", "rl_vs_heuristic", "map50_drop", 0.01, False),
)


def goals(result: dict[str, Any]) -> list[dict[str, Any]]:
    """Each target of the headline against the pooled figures: measured value and met or not."""
    pooled = result.get("pooled", {})
    out = []
    for name, entry, key, bound, at_least in GOALS:
        if entry is None:  # static minus the best other policy
            maps = [v["map50"] for p, v in pooled.items() if p != "static" and v["map50"] is not None]
            static = pooled.get("static", {}).get("map50")
            value = None if static is None or not maps else round(static - max(maps), 4)
        else:
            value = result.get("summary", {}).get(entry, {}).get(key)
        met = None if value is None else (value >= bound if at_least else value <= bound)
        out.append({"goal": name, "measured": value, "met": met})
    return out


def headline(result: dict[str, Any]) -> list[str]:
    """The summary in sentences: each comparison, then the intervals of the mAP differences."""
    lines = [f"{name.replace('_', ' ')}: {reduction_text(v.get('load_reduction'))} accelerator load, "
             f"{reduction_text(v.get('bandwidth_read_reduction'))} read-sensor bandwidth "
             f"({reduction_text(v.get('bandwidth_reduction'))} of all sensors), mAP@0.5 {drop_text(v['map50_drop'])}"
             for name, v in result.get("summary", {}).items()]
    diffs = result.get("statistics", {}).get("pooled", {}).get("map50_difference_95", {})
    lines += [f"mAP@0.5 {name.replace('_', ' ')}: 95 % interval [{interval[0]:+.3f}, {interval[1]:+.3f}] "
              "(bootstrap over worlds)" for name, interval in diffs.items() if interval]
    return lines


def _bars(ax: Any, scenarios: list[str], policies: list[str], values: dict[str, list[float]],
          labels: dict[str, list[str]] | None = None,
          ranges: dict[str, list[list[float] | None]] | None = None) -> None:
    """Grouped bars, one group per scenario; ``ranges``: a [min, max] whisker per bar."""
    width = 0.8 / len(policies)
    x = np.arange(len(scenarios))
    for i, policy in enumerate(policies):
        pos = x - 0.4 + width * (i + 0.5)
        yerr = None
        if ranges:
            spans = [r or [v, v] for r, v in zip(ranges[policy], values[policy], strict=True)]
            yerr = np.array([[max(v - lo, 0.0) for (lo, _), v in zip(spans, values[policy], strict=True)],
                             [max(hi - v, 0.0) for (_, hi), v in zip(spans, values[policy], strict=True)]])
        bars = ax.bar(pos, values[policy], width, color=POLICY_COLORS.get(policy, "#555"), label=policy,
                      yerr=yerr, error_kw={"elinewidth": 0.7, "capsize": 1.5, "ecolor": "#333"})
        if labels:
            for bar, text in zip(bars, labels[policy], strict=True):
                ax.text(bar.get_x() + bar.get_width() / 2, bar.get_height(), text, ha="center", va="bottom",
                        fontsize=5.5, rotation=90)


def figure(result: dict[str, Any], path: Path, title: str = "respecd bench scenarios") -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    settings = result["settings"]
    policies = [p for p in POLICY_ORDER if p in settings]
    scenarios = list(dict.fromkeys(r["scenario"] for r in result["scenarios"]))
    rows = [(m, label) for m, label in MODALITY_ROWS if any(m in settings[p][s] for p in policies for s in scenarios)]
    fig, axes = plt.subplots(len(rows) + 3, 1, figsize=(11, 2.0 * (len(rows) + 3)), dpi=110, sharex=True)
    for ax, (modality, label) in zip(axes, rows, strict=False):
        cells = {p: [settings[p][s].get(modality, {}) for s in scenarios] for p in policies}
        _bars(ax, scenarios, policies, {p: [c.get("rate_hz", 0) for c in cells[p]] for p in policies},
              {p: [c.get("setting", "") if c.get("setting") not in (None, "None") else "" for c in cells[p]]
               for p in policies})
        ax.set_ylabel(label, fontsize=8)
        ax.set_ylim(0, 48)  # head room for the rotated setting labels above 30 Hz bars
    table = {(r["scenario"], r["policy"]): r for r in result["scenarios"]}
    ax_map, ax_cpu, ax_bw = axes[len(rows)], axes[len(rows) + 1], axes[len(rows) + 2]
    stats = result.get("statistics", {}).get("scenarios", {})
    ranges = {p: [stats.get(s, {}).get(p, {}).get("map50_range") for s in scenarios] for p in policies}
    sets = result.get("worlds", 1)
    _bars(ax_map, scenarios, policies, {p: [table[(s, p)]["map50"] or 0.0 for s in scenarios] for p in policies},
          ranges=ranges if sets > 1 else None)
    ax_map.set_ylabel("mAP@0.5" + (f"\n(pooled, {sets} world sets;\nwhiskers: min-max)" if sets > 1 else ""),
                      fontsize=8)
    ax_map.set_ylim(0, 1.05)
    _bars(ax_cpu, scenarios, policies,
          {p: [table[(s, p)].get("accelerator_load", 0.0) for s in scenarios] for p in policies})
    ax_cpu.set_ylabel("accelerator load\n(busy share)", fontsize=8)
    ax_cpu.set_ylim(0, 1.05)
    _bars(ax_bw, scenarios, policies,
          {p: [table[(s, p)].get("bandwidth_read_bps", table[(s, p)]["bandwidth_bps"]) / 1e6 for s in scenarios]
           for p in policies})
    ax_bw.set_yscale("log")
    ax_bw.set_ylabel("read-sensor bandwidth\n(MB/s, log scale)", fontsize=8)
    ax_bw.set_xticks(np.arange(len(scenarios)), scenarios, fontsize=8, rotation=15)
    ax_bw.set_xlabel("scenario (bar labels: the setting each policy chose)", fontsize=8)
    axes[0].legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0, title="policy")
    axes[0].set_title(title)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, bbox_inches="tight")  # the legend sits outside the axes, right of the data
    plt.close(fig)
    return path


def main(argv: list[str] | None = None) -> int:
    """Re-draw the figure of a saved ``respecd bench scenarios --json`` result."""
    import argparse
    import json

    from respecd.errors import InputError, report

    parser = argparse.ArgumentParser(prog="python -m respecd.lab.experiment.report", description=main.__doc__)
    parser.add_argument("result", type=Path, help="the JSON result")
    parser.add_argument("png", type=Path, help="the figure to write")
    a = parser.parse_args(argv)
    expected = "expected a `respecd bench scenarios --json` result"
    try:
        result = json.loads(a.result.read_text(encoding="utf-8"))
    except OSError as err:
        return report(InputError(f"{a.result}: cannot read it ({err.strerror or err}); {expected}"), "report")
    except (UnicodeDecodeError, json.JSONDecodeError) as err:
        return report(InputError(f"{a.result}: not JSON ({err}); {expected}"), "report")
    missing = [key for key in ("settings", "scenarios") if not isinstance(result, dict) or key not in result]
    if missing:
        return report(InputError(f"{a.result}: no {', '.join(map(repr, missing))}; {expected}"), "report")
    if a.png.is_dir():
        return report(InputError(f"{a.png}: is a directory; expected the PNG file to write"), "report")
    try:
        print(figure(result, a.png))
    except (KeyError, IndexError, TypeError) as err:
        return report(InputError(f"{a.result}: missing or malformed entry ({err!r}); {expected}"), "report")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
