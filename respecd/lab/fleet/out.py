"""What ``fleet eval`` writes into ``--out DIR``: ``fleet.json`` (pooled + one entry per log),
``fleet.txt`` (the table it prints), ``fleet.png`` (the metrics per log, the mean and its
spread), and ``logs/NAME.json`` (each log's report, in the format ``--replay --report`` writes,
so ``respecd --replay LOG --report logs/NAME.json --policy P`` adds another policy beside it)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from respecd.atomicfile import write_atomically

ROW = (("F1", ("quality", "f1"), "{:.3f}"), ("recall", ("quality", "recall"), "{:.3f}"),
       ("precision", ("quality", "precision"), "{:.3f}"), ("ConfAgg", ("quality", "mean_conf_agg"), "{:.3f}"),
       ("sensor W", ("energy", "mean_w"), "{:.2f}"), ("switches", ("actions", "switches"), "{}"))
POOLED = (("F1", "f1", "{:.3f}"), ("recall", "recall", "{:.3f}"), ("precision", "precision", "{:.3f}"),
          ("ConfAgg", "mean_conf_agg", "{:.3f}"), ("sensor W", "sensor_w", "{:.2f}"),
          ("switches", "switches", "{:.1f}"))


def write(out: Path, document: dict[str, Any], figure: bool = True) -> list[Path]:
    """Write every file; the paths written."""
    logs = out / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    written = [out / "fleet.json", out / "fleet.txt"]
    write_atomically(written[0], (json.dumps(document, indent=1) + "\n").encode())
    write_atomically(written[1], (table(document) + "\n").encode())
    for entry in document["logs"]:
        if entry["report"] is not None:
            report = entry["report"]
            per_log = {"log": report["log"], "policies": {report["policy"]: {k: v for k, v in report.items()
                                                                             if k != "log"}}}
            path = logs / (entry["log"].replace("/", "__") + ".json")
            write_atomically(path, json.dumps(per_log, indent=1).encode())
            written.append(path)
    if figure and (png := plot(document, out / "fleet.png")) is not None:
        written.append(png)
    return written


def table(document: dict[str, Any]) -> str:
    """One row per log (a failed log: its reason), then the mean +- spread over the logs that ran."""
    header = ["log", *(c[0] for c in ROW), "decisions", "unserved s"]
    rows = []
    for entry in document["logs"]:
        report = entry["report"]
        if report is None:
            continue
        unserved = sum(u["seconds"] for u in (report.get("unserved") or {}).values())
        rows.append([entry["log"], *(fmt.format(report[a][b]) for _, (a, b), fmt in ROW),
                     str(len(report["decisions"])), f"{unserved:.1f}"])
    metrics = document["pooled"]["metrics"]
    if rows:
        rows.append(["mean", *(_mean(metrics[key], fmt) for _, key, fmt in POOLED),
                     _mean(metrics["decisions"], "{:.1f}"), _mean(metrics["unserved_s"], "{:.1f}")])
    widths = [max(len(r[i]) for r in [header, *rows]) for i in range(len(header))]
    lines = ["  ".join(c.ljust(w) if i == 0 else c.rjust(w) for i, (c, w) in enumerate(zip(r, widths, strict=True)))
             for r in [header, *rows]]
    pooled = document["pooled"]
    matched = pooled["matched"]
    lines.append(f"{pooled['ran']} of {pooled['logs']} logs ran, policy {', '.join(pooled['policy']) or '-'}; "
                 f"detections matched over all of them: F1 {matched['f1']:.3f} (tp {matched['tp']}, fp "
                 f"{matched['fp']}, fn {matched['fn']}); reference: {', '.join(pooled['reference']) or '-'}")
    lines += [f"failed: {e['log']}: {e['error']}" for e in document["logs"] if e["error"] is not None]
    return "\n".join(lines)


def _mean(spread: dict[str, Any], fmt: str) -> str:
    if spread["mean"] is None:
        return "-"
    return f"{fmt.format(spread['mean'])}±{fmt.format(spread['sd'])}"


def plot(document: dict[str, Any], png: Path) -> Path | None:
    """F1 and sensor power per log, the mean as a line and its spread as a band; None without
    matplotlib (the lab extra)."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return None
    ran = [e for e in document["logs"] if e["report"] is not None]
    if not ran:
        return None
    names = [e["log"] for e in ran]
    panels = (("F1", ("quality", "f1"), "f1"), ("sensor power (W)", ("energy", "mean_w"), "sensor_w"),
              ("unserved (s)", None, "unserved_s"))
    fig, axes = plt.subplots(len(panels), 1, figsize=(max(6.0, 0.5 * len(names) + 3), 7.5), sharex=True)
    for ax, (title, path, key) in zip(axes, panels, strict=True):
        if path is None:
            values = [sum(u["seconds"] for u in (e["report"].get("unserved") or {}).values()) for e in ran]
        else:
            values = [e["report"][path[0]][path[1]] for e in ran]
        spread = document["pooled"]["metrics"][key]
        ax.bar(range(len(names)), values, color="tab:blue", alpha=0.8)
        ax.axhline(spread["mean"], color="tab:red", lw=1, label=f"mean {spread['mean']:.3g}")
        ax.axhspan(spread["mean"] - spread["sd"], spread["mean"] + spread["sd"], color="tab:red", alpha=0.12,
                   label=f"± sd {spread['sd']:.3g}")
        ax.set_title(title, fontsize=9, loc="left")
        ax.legend(fontsize=7, loc="upper right")
        ax.grid(alpha=0.3, axis="y")
    axes[-1].set_xticks(range(len(names)), names, rotation=45, ha="right", fontsize=7)
    policy = ", ".join(document["pooled"]["policy"])
    fig.suptitle(f"fleet eval: {len(ran)} logs under {policy}", fontsize=10)
    fig.tight_layout()
    fig.savefig(png, dpi=90)
    plt.close(fig)
    return png
