"""``fleet sweep``: which reward weights pay on this fleet, from what its logs recorded.

For every point of the grid (``reward.alpha=0,2,4,reward.beta=0.02,0.05``: every combination),
without a replay:

* ``reward``: what the robots' logged decisions earn under those weights (per log mean, then
  mean and spread over logs) — the logged terms re-weighed (``rewards``);
* ``learned``: the table ``fleet learn`` gives under them, and what it would do in the states the
  fleet was in: the modelled sensor power of its greedy configuration, and how often it picks
  what the robot did (``agrees``).

A weight the logged terms cannot redo, or a key outside ``reward.*``/``learning.*`` (thresholds
re-bin the states; the action space is the table's layout), needs a replay: the sweep says so
and how (exit 2). What the learned tables are worth in detections and energy is a replay too:
``fleet eval --policy exploit --table DIR/tables/POINT.npz``.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from typing import Any

from pydantic import BaseModel

from respecd.control.config import Learning, RewardWeights
from respecd.control.reward import sensor_power
from respecd.errors import InputError
from respecd.lab.fleet.learn import learn, order, profile_with
from respecd.lab.fleet.rewards import rewards, unredoable
from respecd.lab.fleet.transitions import LogSteps, learner

SECTIONS: dict[str, type[BaseModel]] = {"reward": RewardWeights, "learning": Learning}


def parse_grid(texts: Sequence[str]) -> dict[str, list[Any]]:
    """``--grid`` values -> {"reward.alpha": [0.0, 2.0], ...} (InputError says what is wrong, or that a
    replay is needed)."""
    grid: dict[str, list[Any]] = {}
    for text in texts:
        key = None
        for item in (p.strip() for p in text.split(",")):
            if "=" in item:
                key, item = (s.strip() for s in item.split("=", 1))
                _check_key(key)
                grid.setdefault(key, [])
            if key is None or not item:
                raise InputError(f"--grid {text}: expected KEY=V1,V2,...[,KEY=...], e.g. reward.alpha=0,2,4")
            grid[key].append(_value(key, item))
    if not grid:
        raise InputError("--grid: give at least one KEY=V1,V2,... (e.g. reward.alpha=0,2,4,reward.beta=0.02,0.05)")
    return grid


def _check_key(key: str) -> None:
    section, _, name = key.partition(".")
    model = SECTIONS.get(section)
    if model is None:
        raise InputError(f"--grid {key}: only reward.* and learning.* can be swept from the logged decisions; "
                         f"{section}.* changes the states or actions the robots logged, so a replay is needed: "
                         "fleet eval LOGS --profile VARIANT, one variant per setting")
    if name not in model.model_fields:
        raise InputError(f"--grid {key}: {section} has no {name!r} (it has {', '.join(model.model_fields)})")


def _value(key: str, text: str) -> Any:
    try:
        return float(text)
    except ValueError:
        return text  # a choice such as reward.delay=slowest; the model validates it


def points(grid: dict[str, list[Any]]) -> list[dict[str, Any]]:
    keys = list(grid)
    return [dict(zip(keys, values, strict=True)) for values in itertools.product(*(grid[k] for k in keys))]


def point_name(point: dict[str, Any]) -> str:
    return ",".join(f"{k.split('.', 1)[1]}={v:g}" if isinstance(v, float) else f"{k.split('.', 1)[1]}={v}"
                    for k, v in point.items())


def sweep(logs: Sequence[LogSteps], grid: dict[str, list[Any]]) -> list[dict[str, Any]]:
    """One row per grid point, in grid order (InputError when a point needs a replay)."""
    ordered = order([s for s in logs if s.error is None])
    if not ordered:
        raise InputError("fleet sweep: no log has recorded decisions to sweep over")
    reference = ordered[0]
    rows = []
    for point in points(grid):
        weights = {k.split(".", 1)[1]: v for k, v in point.items() if k.startswith("reward.")}
        learning = {k.split(".", 1)[1]: v for k, v in point.items() if k.startswith("learning.")}
        _needs_replay(ordered, reference, weights)
        learned = learn(ordered, weights=weights, learning=learning)
        rows.append({"point": point, "name": point_name(point), "reward": _earned(learned.used, ordered, weights),
                     "learned": _policy(learned, reference, weights, learning, ordered), "refused": learned.refused,
                     "table": learned.table})
    return rows


def _needs_replay(logs: Sequence[LogSteps], reference: LogSteps, weights: dict[str, Any]) -> None:
    target = RewardWeights.model_validate({**reference.profile["controller"]["reward"], **weights})
    for log in logs:
        recorded = RewardWeights.model_validate(log.profile["controller"]["reward"])
        cannot = unredoable(recorded, target, "motion" in log.layout["states"]["factors"])
        if cannot:
            why = "; ".join(f"reward.{k}: {v}" for k, v in cannot.items())
            raise InputError(f"fleet sweep: {log.name}: a replay is needed for these weights ({why}): "
                             "fleet eval LOGS --profile VARIANT --policy heuristic|exploit, one variant per setting")


def _earned(used: Sequence[str], logs: Sequence[LogSteps], weights: dict[str, Any]) -> dict[str, Any]:
    """Mean reward per logged decision, per log, then mean and spread over the logs."""
    means = []
    for log in logs:
        if log.name not in used or not log.steps:
            continue
        recorded = RewardWeights.model_validate(log.profile["controller"]["reward"])
        target = RewardWeights.model_validate({**log.profile["controller"]["reward"], **weights})
        paid = rewards(log.steps, recorded, target)
        means.append(math.fsum(paid) / len(paid))
    return _spread(means)


def _policy(learned: Any, reference: LogSteps, weights: dict[str, Any], learning: dict[str, Any],
            logs: Sequence[LogSteps]) -> dict[str, Any]:
    """What the learned table does in the fleet's logged states: sensor watts, agreement, coverage."""
    if learned.table is None:
        return {"updates": 0}
    controller = learner(profile_with(reference.profile, weights, learning))
    learned.table.restore_into(controller.table, controller.layout(), reference.profile["name"])
    space, table = controller.space, controller.table
    watts, agree, acted, seen = [], 0, 0, 0
    names = [slot.name for slot in space.slots]
    for log in logs:
        if log.name not in learned.used:
            continue
        for step in log.steps:
            seen += 1
            action = table.greedy_tried(step.state)
            if action is None:
                continue
            acted += 1
            agree += action == step.action
            if space.mode != "moves":
                requests = space.requests(space.position_of(action))
                watts.append(sensor_power(zip(names, requests, strict=True), controller.powers))
    return {"updates": table.updates, "policy_w": _spread(watts)["mean"],
            "agrees": round(agree / acted, 4) if acted else None,
            "states_learned": round(acted / seen, 4) if seen else None}


def _spread(values: list[float]) -> dict[str, Any]:
    if not values:
        return {"mean": None, "sd": None, "logs": 0}
    mean = math.fsum(values) / len(values)
    sd = math.sqrt(math.fsum((v - mean) ** 2 for v in values) / len(values))
    return {"mean": round(mean, 6), "sd": round(sd, 6), "logs": len(values)}


def table(rows: Sequence[dict[str, Any]]) -> str:
    header = ["point", "reward/decision", "policy W", "agrees", "states learned", "updates"]
    lines = []
    for row in rows:
        reward, policy = row["reward"], row["learned"]
        lines.append([row["name"], "-" if reward["mean"] is None else f"{reward['mean']:.4f}±{reward['sd']:.4f}",
                      _fmt(policy.get("policy_w"), "{:.2f}"), _fmt(policy.get("agrees"), "{:.0%}"),
                      _fmt(policy.get("states_learned"), "{:.0%}"), str(policy.get("updates", 0))])
    widths = [max(len(r[i]) for r in [header, *lines]) for i in range(len(header))]
    return "\n".join("  ".join(c.ljust(w) if i == 0 else c.rjust(w) for i, (c, w) in enumerate(zip(r, widths,
                                                                                                  strict=True)))
                     for r in [header, *lines])


def _fmt(value: Any, fmt: str) -> str:
    return "-" if value is None else fmt.format(value)
