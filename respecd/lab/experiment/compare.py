"""The headline comparison: the scenarios in sequence under static, the heuristics and RL,
on one or more sets of worlds.

Each policy drives its own controller through the same pieces (same worlds, same sample
instants), one continuous run per world set, as the paper runs its scenarios back to back;
a fresh controller starts each set. The policies: ``static`` (everything at its maximum),
``heuristic`` (the tuned rules, ``heuristic.py``), ``rl`` (the Q-table) and, on request,
``old-heuristic`` (the documented rules alone). Per scenario and policy, pooled over the sets:

* ``action``: the stabilized configuration, the one active longest over the scenario's
  second half (after the controller has settled);
* ``map50``: COCO AP@0.5 of what the daemon would have delivered at the sample instants
  (the detector's last finished inference, stale as it is) against ground truth then;
* ``accelerator_load``: the accelerator's busy share (0..1; the paper's GPU load: one
  accelerator, a drop-oldest queue before it, ``accelerator.py``);
* ``compute_ms_per_s``: detector time the configuration asks for per second (uncapped:
  forward time x the rate of new detector inputs + one attribution); above 1000 one
  accelerator cannot keep up and the daemon drops bundles (``dropped_per_window``);
* ``energy_j``: the profile's sensor power model over the configurations that ran plus the
  accelerator's power (``accelerator_j``: busy share x the platform's figure);
* ``bandwidth_bps``: sensing bytes per second (raw pixels, radar UART packets, IMU), and
  ``bandwidth_read_bps``: of the sensors the detector reads.

``pooled`` pools each policy's images over every scenario of every set into one mAP@0.5 and
averages the per-window figures over every window; its energy is the mean over sets of one
run's total. ``spread`` is each of those figures' [min, max] over the sets, ``sets`` the
figures of each set. The summary compares the pooled figures of RL with static and with the
tuned heuristic: ``load_reduction = 1 - rl / baseline`` (accelerator load), likewise
``compute_reduction``, ``bandwidth_reduction`` and ``bandwidth_read_reduction``, and
``map50_drop = baseline - rl`` (absolute). ``statistics`` says what each mAP rests on and how
sure it is (``stats.py``: a bootstrap over worlds).
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from respecd.control.config import HeuristicRules
from respecd.control.persist import fingerprint, read_table
from respecd.errors import InputError
from respecd.lab.detector.metrics import ImageResult, average_precision
from respecd.lab.experiment.rollout import Piece, Rollout, WindowRecord, controller_for
from respecd.lab.experiment.stats import WorldBootstrap, counts

if TYPE_CHECKING:
    from respecd.config import Profile

POLICIES = ("static", "heuristic", "rl")
OLD_HEURISTIC = "old-heuristic"  # the documented rules alone, beside the tuned ones on request
METRICS = ("map50", "accelerator_load", "compute_ms_per_s", "energy_j", "bandwidth_bps", "bandwidth_read_bps")
Runs = list[list[WindowRecord]]  # one list of window records per world set


def rl_controller(profile: Profile, table_path: Path) -> Any:
    """An exploiting controller with the table at ``table_path`` (must match the profile's spaces)."""
    controller = controller_for(profile, "exploit")
    assert controller.table is not None  # exploit learns into a table
    meta, q, visits = read_table(table_path)
    if meta.get("fingerprint") != fingerprint(controller.layout()) or q.shape != controller.table.shape:
        raise InputError(f"{table_path}: Q-table was learned for another state/action space than profile "
                         f"{profile.name!r} (fingerprint {meta.get('fingerprint')}); pass the profile it was "
                         f"trained with (--profile; the table names {meta.get('profile', '?')!r}) or retrain "
                         "with `respecd train-policy`")
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


def world_seed_range(first_seed: int, count: int, scenarios: Sequence[str]) -> list[int]:
    """The first and last world seed of ``world_sets(scenarios, first_seed, count, ...)``."""
    return [first_seed, first_seed + count * len(scenarios) - 1]


def stabilized(runs: Sequence[Sequence[WindowRecord]]) -> Any:
    """The configuration active longest over the second halves of the runs (one per world set)."""
    tails = [r for records in runs for r in (records[len(records) // 2:] or records)]
    return Counter(r.position for r in tails).most_common(1)[0][0]


def figures(runs: Runs) -> dict[str, Any]:
    """Pooled mAP@0.5, the per-window figures averaged over every window, energy per set."""
    windows = [r for records in runs for r in records]
    return {"map50": _map50([im for r in windows for im in r.images]),
            "accelerator_load": round(float(np.mean([r.load.busy for r in windows])), 4),
            "compute_ms_per_s": round(float(np.mean([r.compute_ms for r in windows])), 1),
            "dropped_per_window": round(float(np.mean([r.load.dropped for r in windows])), 2),
            "energy_j": round(float(np.mean([sum(r.energy_j for r in records) for records in runs])), 2),
            "accelerator_j": round(float(np.mean([sum(r.accelerator_j for r in records) for records in runs])), 2),
            "bandwidth_bps": round(float(np.mean([r.bandwidth_bps for r in windows])), 0),
            "bandwidth_read_bps": round(float(np.mean([r.bandwidth_read_bps for r in windows])), 0)}


def _of(runs: Runs, scenario: str) -> Runs:
    return [[r for r in records if r.scenario == scenario] for records in runs]


def scenarios_of(runs: Runs) -> list[str]:
    return list(dict.fromkeys(r.scenario for records in runs for r in records))


def scenario_rows(policy: str, controller: Any, runs: Runs) -> list[dict[str, Any]]:
    rows = []
    for scenario in scenarios_of(runs):
        mine = _of(runs, scenario)
        rows.append({"scenario": scenario, "policy": policy,
                     "action": controller.space.describe_position(stabilized(mine)), **figures(mine)})
    return rows


def _versus(rl: dict[str, Any], base: dict[str, Any]) -> dict[str, float | None]:
    def reduction(key: str) -> float | None:
        return round(1.0 - rl[key] / base[key], 4) if base[key] else None

    drop = base["map50"] - rl["map50"] if rl["map50"] is not None and base["map50"] is not None else None
    return {"load_reduction": reduction("accelerator_load"), "compute_reduction": reduction("compute_ms_per_s"),
            "map50_drop": None if drop is None else round(drop, 4), "bandwidth_reduction": reduction("bandwidth_bps"),
            "bandwidth_read_reduction": reduction("bandwidth_read_bps")}


def pooled(records: dict[str, Runs]) -> dict[str, dict[str, Any]]:
    """Per policy over every world set: pooled mAP@0.5, mean compute and bandwidth, energy per set."""
    return {p: figures(runs) for p, runs in records.items()}


def spread(records: dict[str, Runs]) -> dict[str, dict[str, list[Any]]]:
    """Per policy and figure, [min, max] over the world sets."""
    out: dict[str, dict[str, list[Any]]] = {}
    for policy, runs in records.items():
        per_set = [figures([records_k]) for records_k in runs]
        out[policy] = {}
        for metric in METRICS:
            values = [v[metric] for v in per_set if v[metric] is not None]
            out[policy][metric] = [min(values), max(values)] if values else [None, None]
    return out


def summary(totals: dict[str, dict[str, Any]]) -> dict[str, Any]:
    return {"rl_vs_static": _versus(totals["rl"], totals["static"]),
            "rl_vs_heuristic": _versus(totals["rl"], totals["heuristic"])}


def _controllers(profile: Profile, table_path: Path, rules: HeuristicRules, old: bool) -> dict[str, Any]:
    """Every policy's controller; the tuned heuristic with ``rules``, the old one with the profile's."""
    out = {"static": controller_for(profile, "static"), "heuristic": controller_for(profile, "heuristic", rules),
           "rl": rl_controller(profile, table_path)}
    if old:
        out[OLD_HEURISTIC] = controller_for(profile, "heuristic")
    return out


def run_sets(profile: Profile, rollout: Rollout, sets: list[list[Piece]], table_path: Path,
             on_window: Callable[[str, WindowRecord], None] | None = None,
             people: Callable[[Piece], int] | None = None, rules: HeuristicRules | None = None,
             old_heuristic: bool = False) -> dict[str, Any]:
    """Every policy over every world set; the JSON body of ``respecd bench scenarios``.

    ``people(piece)``: how many persons the piece's world holds (for the statistics);
    ``rules``: the tuned heuristic's (default ``heuristic.TUNED``); ``old_heuristic``: run the
    documented rules alone too.
    """
    from respecd.lab.experiment.heuristic import TUNED

    policies = (*POLICIES, OLD_HEURISTIC) if old_heuristic else POLICIES
    records: dict[str, Runs] = {p: [] for p in policies}
    controllers: dict[str, Any] = {}
    for pieces in sets:
        # each set starts fresh, as a new run of the robot
        controllers = _controllers(profile, table_path, rules or TUNED, old_heuristic)
        for policy, controller in controllers.items():
            callback = (lambda r, p=policy: on_window(p, r)) if on_window else None
            records[policy].append(rollout.run(controller, pieces, callback))
    rows = [row for p in policies for row in scenario_rows(p, controllers[p], records[p])]
    order = {p.scenario: i for i, p in enumerate(sets[0])}
    rows.sort(key=lambda r: (order[r["scenario"]], policies.index(r["policy"])))
    totals = pooled(records)
    return {"scenarios": rows, "summary": summary(totals), "pooled": totals, "spread": spread(records),
            "sets": _per_set(sets, records), "statistics": statistics(records, sets, people),
            "settings": {p: _settings(controllers[p], records[p]) for p in policies}}


def _per_set(sets: list[list[Piece]], records: dict[str, Runs]) -> list[dict[str, Any]]:
    out = []
    for k, pieces in enumerate(sets):
        totals = {p: figures([records[p][k]]) for p in records}
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
