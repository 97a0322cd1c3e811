"""The headline comparison: the six scenarios in sequence under static, heuristic and RL.

Each policy drives its own controller through the same pieces (same worlds, same sample
instants), one continuous run, as the paper runs its six scenarios back to back. Per
scenario and policy:

* ``action``: the stabilized configuration, the one active longest over the scenario's
  second half (after the controller has settled);
* ``map50``: COCO AP@0.5 of the detections at the sample instants against ground truth at
  those instants;
* ``compute_ms_per_s``: measured detector wall time per second (``latency.py``); / 1000 is
  the share of one core;
* ``energy_j``: the profile's power model over the configurations that ran;
* ``bandwidth_bps``: sensing bytes per second (raw pixels, radar UART packets, IMU).

The summary pools each policy's images over all six scenarios into one mAP@0.5 and averages
compute over the whole run: ``compute_reduction = 1 - rl / baseline`` and
``map50_drop = baseline - rl`` (absolute).
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from respecd.control.persist import fingerprint, read_table
from respecd.errors import InputError
from respecd.lab.detector.metrics import ImageResult, average_precision
from respecd.lab.experiment.rollout import Piece, Rollout, WindowRecord, controller_for

POLICIES = ("static", "heuristic", "rl")


def rl_controller(profile: Any, table_path: Path) -> Any:
    """An exploiting controller with the table at ``table_path`` (must match the profile's spaces)."""
    controller = controller_for(profile, "exploit")
    assert controller.table is not None  # exploit learns into a table
    meta, q, visits = read_table(table_path)
    if meta.get("fingerprint") != fingerprint(controller.layout()) or q.shape != controller.table.shape:
        raise InputError(f"{table_path}: Q-table was learned for another state/action space than profile "
                         f"{profile.name!r} (fingerprint {meta.get('fingerprint')}); retrain with "
                         "`respecd train-policy`")
    controller.table.restore(q, visits, int(meta.get("updates", 0)), float(meta.get("epsilon", 0.0)))
    return controller


def _map50(images: list[ImageResult]) -> float | None:
    value = average_precision(images, 0.5)
    return None if np.isnan(value) else round(float(value), 4)


def stabilized(records: Sequence[WindowRecord]) -> Any:
    """The configuration active longest over the second half of the records."""
    tail = records[len(records) // 2:] or records
    return Counter(r.position for r in tail).most_common(1)[0][0]


def scenario_rows(policy: str, controller: Any, records: list[WindowRecord]) -> list[dict[str, Any]]:
    rows = []
    for scenario in dict.fromkeys(r.scenario for r in records):
        mine = [r for r in records if r.scenario == scenario]
        rows.append({
            "scenario": scenario,
            "policy": policy,
            "action": controller.space.describe_position(stabilized(mine)),
            "map50": _map50([im for r in mine for im in r.images]),
            "compute_ms_per_s": round(float(np.mean([r.compute_ms for r in mine])), 1),
            "energy_j": round(float(sum(r.energy_j for r in mine)), 2),
            "bandwidth_bps": round(float(np.mean([r.bandwidth_bps for r in mine])), 0),
        })
    return rows


def _versus(rl: dict[str, float | None], base: dict[str, float | None]) -> dict[str, float | None]:
    reduction = 1.0 - rl["compute"] / base["compute"] if base["compute"] else None  # type: ignore[operator]
    drop = base["map50"] - rl["map50"] if rl["map50"] is not None and base["map50"] is not None else None
    return {"compute_reduction": None if reduction is None else round(reduction, 4),
            "map50_drop": None if drop is None else round(drop, 4)}


def overall(records: dict[str, list[WindowRecord]]) -> dict[str, dict[str, Any]]:
    """Per policy over the whole run: pooled mAP@0.5, mean compute, total energy, mean bandwidth."""
    return {p: {"map50": _map50([im for r in recs for im in r.images]),
                "compute_ms_per_s": round(float(np.mean([r.compute_ms for r in recs])), 1),
                "energy_j": round(float(sum(r.energy_j for r in recs)), 2),
                "bandwidth_bps": round(float(np.mean([r.bandwidth_bps for r in recs])), 0)}
            for p, recs in records.items()}


def summary(totals: dict[str, dict[str, Any]]) -> dict[str, Any]:
    def pick(p: str) -> dict[str, Any]:
        return {"map50": totals[p]["map50"], "compute": totals[p]["compute_ms_per_s"]}

    return {"rl_vs_static": _versus(pick("rl"), pick("static")),
            "rl_vs_heuristic": _versus(pick("rl"), pick("heuristic"))}


def run_all(profile: Any, rollout: Rollout, pieces: list[Piece], table_path: Path,
            on_window: Callable[[str, WindowRecord], None] | None = None) -> dict[str, Any]:
    """Every policy over ``pieces``; the JSON body of ``respecd bench scenarios``."""
    controllers = {"static": controller_for(profile, "static"), "heuristic": controller_for(profile, "heuristic"),
                   "rl": rl_controller(profile, table_path)}
    records: dict[str, list[WindowRecord]] = {}
    rows: list[dict[str, Any]] = []
    positions: dict[str, dict[str, Any]] = {}
    for policy, controller in controllers.items():
        callback = (lambda r, p=policy: on_window(p, r)) if on_window else None
        records[policy] = rollout.run(controller, pieces, callback)
        rows += scenario_rows(policy, controller, records[policy])
        positions[policy] = _settings(controller, records[policy])
    order = {p.scenario: i for i, p in enumerate(pieces)}
    rows.sort(key=lambda r: (order[r["scenario"]], POLICIES.index(r["policy"])))
    totals = overall(records)
    return {"scenarios": rows, "summary": summary(totals), "overall": totals, "settings": positions}


def _settings(controller: Any, records: list[WindowRecord]) -> dict[str, Any]:
    """Per scenario, the stabilized setting and rate of every controlled sensor (for the figure)."""
    out: dict[str, Any] = {}
    for scenario in dict.fromkeys(r.scenario for r in records):
        position = stabilized([r for r in records if r.scenario == scenario])
        cells = {}
        for slot, (setting, rate) in zip(controller.space.slots, position, strict=True):
            value = slot.settings[setting]
            label = f"{value[0]}x{value[1]}" if isinstance(value, tuple) else str(value)
            cells[slot.modality] = {"setting": label, "rate_hz": slot.rates[rate]}
        out[scenario] = cells
    return out
