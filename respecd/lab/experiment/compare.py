"""The headline comparison: the scenarios in sequence under static, heuristic and RL, on
one or more sets of worlds.

Each policy drives its own controller through the same pieces (same worlds, same sample
instants), one continuous run per world set, as the paper runs its scenarios back to back;
a fresh controller starts each set. Per scenario and policy, pooled over the sets:

* ``action``: the stabilized configuration, the one active longest over the scenario's
  second half (after the controller has settled);
* ``map50``: COCO AP@0.5 of the detections at the sample instants against ground truth at
  those instants;
* ``compute_ms_per_s``: measured detector wall time per second (``latency.py``); / 1000 is
  the share of one core;
* ``energy_j``: the profile's power model over the configurations that ran;
* ``bandwidth_bps``: sensing bytes per second (raw pixels, radar UART packets, IMU).

``pooled`` pools each policy's images over every scenario of every set into one mAP@0.5 and
averages compute and bandwidth over every window; its energy is the mean over sets of one
run's total. ``spread`` is each of those figures' [min, max] over the sets, ``sets`` the
figures of each set. The summary compares the pooled figures:
``compute_reduction = 1 - rl / baseline``, ``bandwidth_reduction`` likewise and
``map50_drop = baseline - rl`` (absolute). ``statistics`` says what each mAP rests on and how
sure it is (``stats.py``: a bootstrap over worlds).
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from respecd.control.persist import fingerprint, read_table
from respecd.errors import InputError
from respecd.lab.detector.metrics import ImageResult, average_precision
from respecd.lab.experiment.rollout import Piece, Rollout, WindowRecord, controller_for
from respecd.lab.experiment.stats import WorldBootstrap, counts

if TYPE_CHECKING:
    from respecd.config import Profile

POLICIES = ("static", "heuristic", "rl")
METRICS = ("map50", "compute_ms_per_s", "energy_j", "bandwidth_bps")
Runs = list[list[WindowRecord]]  # one list of window records per world set


def rl_controller(profile: Profile, table_path: Path) -> Any:
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


def world_sets(scenarios: Sequence[str], first_seed: int, count: int, duration_s: float) -> list[list[Piece]]:
    """``count`` sets of one world per scenario, seeds ``first_seed`` .. ``first_seed + count·S − 1``
    (set ``k``, scenario ``j``: ``first_seed + k·S + j``; S scenarios), all distinct."""
    n = len(scenarios)
    return [[Piece(name, first_seed + k * n + j, duration_s) for j, name in enumerate(scenarios)]
            for k in range(count)]


def stabilized(runs: Sequence[Sequence[WindowRecord]]) -> Any:
    """The configuration active longest over the second halves of the runs (one per world set)."""
    tails = [r for records in runs for r in (records[len(records) // 2:] or records)]
    return Counter(r.position for r in tails).most_common(1)[0][0]


def _figures(runs: Runs) -> dict[str, Any]:
    """Pooled mAP@0.5, mean compute and bandwidth per window, mean energy per set."""
    windows = [r for records in runs for r in records]
    return {"map50": _map50([im for r in windows for im in r.images]),
            "compute_ms_per_s": round(float(np.mean([r.compute_ms for r in windows])), 1),
            "energy_j": round(float(np.mean([sum(r.energy_j for r in records) for records in runs])), 2),
            "bandwidth_bps": round(float(np.mean([r.bandwidth_bps for r in windows])), 0)}


def _of(runs: Runs, scenario: str) -> Runs:
    return [[r for r in records if r.scenario == scenario] for records in runs]


def scenarios_of(runs: Runs) -> list[str]:
    return list(dict.fromkeys(r.scenario for records in runs for r in records))


def scenario_rows(policy: str, controller: Any, runs: Runs) -> list[dict[str, Any]]:
    rows = []
    for scenario in scenarios_of(runs):
        mine = _of(runs, scenario)
        rows.append({"scenario": scenario, "policy": policy,
                     "action": controller.space.describe_position(stabilized(mine)), **_figures(mine)})
    return rows


def _versus(rl: dict[str, Any], base: dict[str, Any]) -> dict[str, float | None]:
    def reduction(key: str) -> float | None:
        return round(1.0 - rl[key] / base[key], 4) if base[key] else None

    drop = base["map50"] - rl["map50"] if rl["map50"] is not None and base["map50"] is not None else None
    return {"compute_reduction": reduction("compute_ms_per_s"), "map50_drop": None if drop is None else round(drop, 4),
            "bandwidth_reduction": reduction("bandwidth_bps")}


def pooled(records: dict[str, Runs]) -> dict[str, dict[str, Any]]:
    """Per policy over every world set: pooled mAP@0.5, mean compute and bandwidth, energy per set."""
    return {p: _figures(runs) for p, runs in records.items()}


def spread(records: dict[str, Runs]) -> dict[str, dict[str, list[Any]]]:
    """Per policy and figure, [min, max] over the world sets."""
    out: dict[str, dict[str, list[Any]]] = {}
    for policy, runs in records.items():
        per_set = [_figures([records_k]) for records_k in runs]
        out[policy] = {}
        for metric in METRICS:
            values = [v[metric] for v in per_set if v[metric] is not None]
            out[policy][metric] = [min(values), max(values)] if values else [None, None]
    return out


def summary(totals: dict[str, dict[str, Any]]) -> dict[str, Any]:
    return {"rl_vs_static": _versus(totals["rl"], totals["static"]),
            "rl_vs_heuristic": _versus(totals["rl"], totals["heuristic"])}


def _controllers(profile: Profile, table_path: Path) -> dict[str, Any]:
    return {"static": controller_for(profile, "static"), "heuristic": controller_for(profile, "heuristic"),
            "rl": rl_controller(profile, table_path)}


def run_all(profile: Profile, rollout: Rollout, pieces: list[Piece], table_path: Path,
            on_window: Callable[[str, WindowRecord], None] | None = None) -> dict[str, Any]:
    """Every policy over ``pieces`` (one world set)."""
    return run_sets(profile, rollout, [pieces], table_path, on_window)


def run_sets(profile: Profile, rollout: Rollout, sets: list[list[Piece]], table_path: Path,
             on_window: Callable[[str, WindowRecord], None] | None = None,
             people: Callable[[Piece], int] | None = None) -> dict[str, Any]:
    """Every policy over every world set; the JSON body of ``respecd bench scenarios``.

    ``people(piece)``: how many persons the piece's world holds (for the statistics).
    """
    records: dict[str, Runs] = {p: [] for p in POLICIES}
    controllers: dict[str, Any] = {}
    for pieces in sets:
        controllers = _controllers(profile, table_path)  # each set starts fresh, as a new run of the robot
        for policy, controller in controllers.items():
            callback = (lambda r, p=policy: on_window(p, r)) if on_window else None
            records[policy].append(rollout.run(controller, pieces, callback))
    rows = [row for p in POLICIES for row in scenario_rows(p, controllers[p], records[p])]
    order = {p.scenario: i for i, p in enumerate(sets[0])}
    rows.sort(key=lambda r: (order[r["scenario"]], POLICIES.index(r["policy"])))
    totals = pooled(records)
    return {"scenarios": rows, "summary": summary(totals), "pooled": totals, "spread": spread(records),
            "sets": _per_set(sets, records), "statistics": statistics(records, sets, people),
            "settings": {p: _settings(controllers[p], records[p]) for p in POLICIES}}


def _per_set(sets: list[list[Piece]], records: dict[str, Runs]) -> list[dict[str, Any]]:
    out = []
    for k, pieces in enumerate(sets):
        totals = {p: _figures([records[p][k]]) for p in records}
        out.append({"seeds": [piece.seed for piece in pieces], "pooled": totals, "summary": summary(totals)})
    return out


def statistics(records: dict[str, Runs], sets: list[list[Piece]],
               people: Callable[[Piece], int] | None) -> dict[str, Any]:
    """What each mAP rests on, and the bootstrap over worlds (``stats.py``)."""
    names = scenarios_of(records["static"])
    images = {p: {s: [[im for r in records_k for im in r.images] for records_k in _of(runs, s)] for s in names}
              for p, runs in records.items()}
    boot = WorldBootstrap(images)
    by_scenario = {}
    for s in names:
        persons = None if people is None else [people(pc) for pieces in sets for pc in pieces if pc.scenario == s]
        by_scenario[s] = {**counts(images["static"][s], persons), **boot.scenario(s)}
    return {"scenarios": by_scenario, "pooled": boot.pooled()}


def _settings(controller: Any, runs: Runs) -> dict[str, Any]:
    """Per scenario, the stabilized setting and rate of every controlled sensor (for the figure)."""
    out: dict[str, Any] = {}
    for scenario in scenarios_of(runs):
        position = stabilized(_of(runs, scenario))
        cells = {}
        for slot, (setting, rate) in zip(controller.space.slots, position, strict=True):
            value = slot.settings[setting]
            label = f"{value[0]}x{value[1]}" if isinstance(value, tuple) else str(value)
            cells[slot.modality] = {"setting": label, "rate_hz": slot.rates[rate]}
        out[scenario] = cells
    return out
