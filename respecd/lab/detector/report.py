"""Evaluation output: Markdown tables (mAP per resolution and condition, mAP with each sensor off,
contributions and faithfulness), a PNG bar chart of the contributions per condition, and the raw JSON."""

from __future__ import annotations

import json
import math
from pathlib import Path

from respecd.lab.detector.evaluate import REDUNDANCY, condition_order


def _fmt(v: float | None) -> str:
    return "n/a" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.3f}"


def _resolution_table(report: dict, conds: list[str]) -> list[str]:
    sizes = list(report.get("by_resolution", {}))
    if not sizes:
        return []
    rows = report["by_resolution"]
    lines = ["mAP@0.5 with every sensor on, per RGB resolution (heads: detections >= 0.25 from P3 / P4 / P5)", "",
             "| condition | " + " | ".join(sizes) + " |", "|---|" + "---|" * len(sizes)]
    lines.append("| all | " + " | ".join(_fmt(rows[s]["map50"]) for s in sizes) + " |")
    for cond in conds:
        if cond != "all":
            lines.append(f"| {cond} | " + " | ".join(_fmt(rows[s]["by_condition"].get(cond)) for s in sizes) + " |")
    lines.append("| heads | " + " | ".join(" / ".join(str(v) for v in rows[s]["levels"].values()) for s in sizes)
                 + " |")
    lines.append("| tallest detection (px) | " + " | ".join(f"{rows[s]['tallest_detection_px']:.0f}" for s in sizes)
                 + " |")
    for share in rows[sizes[0]].get("recall_by_height", {}).get("all", {}):  # people found, by height share
        lines.append(f"| found >= 0.25, height {share} of frame | "
                     + " | ".join("{} of {}".format(*rows[s]["recall_by_height"]["all"][share]) for s in sizes) + " |")
    for cond in conds:  # mAP@0.5 of the boxes the daemon delivers ("all" first)
        if cond in rows[sizes[0]].get("delivered_map50", {}):
            lines.append(f"| delivered boxes (>= 0.25) only, {cond} | "
                         + " | ".join(_fmt(rows[s]["delivered_map50"][cond]) for s in sizes) + " |")
    for cond in conds:  # false boxes >= 0.25, by kind ("all" first)
        if cond in rows[sizes[0]].get("false_boxes", {}):
            lines.append(f"| false boxes >= 0.25, {cond} (second / misplaced / clutter) | " + " | ".join(
                " / ".join(str(v) for v in rows[s]["false_boxes"][cond].values()) for s in sizes) + " |")
    return lines + [""]


def markdown(report: dict, title: str) -> str:
    """mAP per resolution; mAP@0.5 / mAP@0.5:0.95 with each sensor off; contributions and faithfulness."""
    conds = condition_order(report)
    names = list(report["map"][conds[0]])
    size = report.get("attribution", {}).get("rgb")
    lines = [f"# {title}", "", *_resolution_table(report, conds)]
    lines += [f"mAP@0.5 / mAP@0.5:0.95 at {size}, every sensor on and each one off", ""]
    lines.append("| condition | frames | " + " | ".join(names) + " |")
    lines.append("|---|---|" + "---|" * len(names))
    for cond in conds:
        cells = [f"{_fmt(report['map'][cond][n]['map50'])} / {_fmt(report['map'][cond][n]['map50_95'])}" for n in names]
        lines.append(f"| {cond} | {report['frames'][cond]} | " + " | ".join(cells) + " |")
    keys = _contribution_keys(report)
    method = report.get("attribution", {}).get("method", "?")
    lines += ["", f"Mean contribution ({method}; frames with a detection) and faithfulness (share of attributed "
                  "boxes whose top-ranked sensor costs more when off than the second-ranked)", ""]
    lines.append("| condition | attributed | " + " | ".join(keys) + " | boxes | faithfulness |")
    lines.append("|---|---|" + "---|" * (len(keys) + 2))
    for cond in conds:
        row = report["contributions"].get(cond, {})
        lines.append(f"| {cond} | {report['attributed'].get(cond, 0)} | "
                     + " | ".join(_fmt(row.get(k)) if row else "n/a" for k in keys)
                     + f" | {report['attributed_detections'].get(cond, 0)} | "
                     + f"{_fmt(report['faithfulness'].get(cond))} |")
    return "\n".join(lines + _redundancy_table(report, conds)) + "\n"


REDUNDANCY_WORDS = {"dependence": "lost with it off (dependence)", "sufficiency": "kept with only it on (sufficiency)",
                    "shapley": "credited by the Shapley value",
                    "lost_when_off": "lost in a whole sensor-off pass (lost_when_off: what dependence predicts)"}


def _redundancy_table(report: dict, conds: list[str]) -> list[str]:
    """Per sensor: share of the attributed boxes' confidence lost with it off, kept with only it on, Shapley."""
    names = [n for n in REDUNDANCY if report.get(n)]
    keys = [k for k in _contribution_keys(report) if k not in ("r", "g", "b")]
    if not names:
        return []
    lines = ["", "Per sensor, share of the attributed boxes' confidence "
             + ", ".join(REDUNDANCY_WORDS[n] for n in names) + ": " + " / ".join(names), "",
             "| condition | " + " | ".join(keys) + " |", "|---|" + "---|" * len(keys)]
    for cond in conds:
        cells = [" / ".join(_fmt(report[n].get(cond, {}).get(k)) for n in names) for k in keys]
        lines.append(f"| {cond} | " + " | ".join(cells) + " |")
    return lines


def _contribution_keys(report: dict) -> list[str]:
    for row in report["contributions"].values():
        if row:
            ordered = [k for k in ("r", "g", "b", "rgb") if k in row]
            return ordered + [k for k in row if k not in ordered]
    return ["rgb"]


def bar_chart(report: dict, path: Path, title: str) -> None:
    """Grouped bars: per condition, the mean contribution of each modality (RGB grouped)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    conds = [c for c in condition_order(report) if report["contributions"].get(c)]
    keys = [k for k in _contribution_keys(report) if k not in ("r", "g", "b")]
    fig, ax = plt.subplots(figsize=(8, 3.6), dpi=120)
    width = 0.8 / max(1, len(keys))
    for i, key in enumerate(keys):
        xs = [j + (i - (len(keys) - 1) / 2) * width for j in range(len(conds))]
        ax.bar(xs, [report["contributions"][c].get(key, 0.0) for c in conds], width, label=key)
    ax.set_xticks(range(len(conds)), conds, fontsize=8)
    ax.set_xlabel("scene condition")
    ax.set_ylim(0, 1)
    ax.set_ylabel("mean contribution (0-1)")
    ax.set_title(title, fontsize=9)
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8, title="modality")  # outside the bars
    fig.tight_layout()
    fig.savefig(path, bbox_inches="tight")
    plt.close(fig)


def write(report: dict, out_dir: Path, title: str, summary: dict | None = None) -> dict[str, str]:
    """eval.md, contributions.png and eval.json (the report, with ``summary``'s top-level keys first)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = {"markdown": out_dir / "eval.md", "png": out_dir / "contributions.png", "json": out_dir / "eval.json"}
    paths["markdown"].write_text(markdown(report, title), encoding="utf-8")
    bar_chart(report, paths["png"], title)
    body = {**(summary or {}), **{k: v for k, v in report.items() if k not in (summary or {})}}
    for key in ("contributions", *REDUNDANCY):  # the summary's scene means; per condition beside them
        if summary and key in summary:
            body[f"{key}_by_condition"] = report[key]
    paths["json"].write_text(json.dumps(body, indent=2, default=float) + "\n", encoding="utf-8")
    return {k: str(v) for k, v in paths.items()}
