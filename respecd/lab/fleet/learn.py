"""``fleet learn``: one Q-table from many logs — their recorded transitions through one learner.

Reading each log's decisions is the per-log work (parallel on any backend); the updates then
run in one fixed order: the logs by start time (then name), each log's decisions in their
order, through one ``Controller.learn`` — the very update the robot's controller made. So the
table is exact (it is what one learner fed those logs one after another would hold) and the
same bit for bit whatever the backend, the worker count or the order the logs were given in.
Q-learning is off-policy: logs recorded under any policy teach the same table.

The fleet's profile is ``--profile`` or the first log's; a log of another layout is reported,
not learned from. Each log's rewards are its own logged rewards where its reward weights are
the fleet's, else re-weighed from its logged terms (``rewards``); where that cannot be done
exactly the log is reported with why (a replay is needed).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from respecd.control.config import RewardWeights
from respecd.control.persist import StoredTable, mismatch, table_meta
from respecd.lab.fleet.rewards import rewards, unredoable
from respecd.lab.fleet.transitions import LogSteps, learner

MERGE = ("sequential: each log's recorded transitions (its decisions in their order) through one Q-learner, the "
         "logs by start time then name; logs read in parallel, updates in that one order")


@dataclass(frozen=True)
class Learned:
    """The table, the logs it learned from (in order), and the logs it could not use, with why."""

    table: StoredTable | None
    used: tuple[str, ...]
    transitions: int
    refused: dict[str, str]


def order(logs: Sequence[LogSteps]) -> list[LogSteps]:
    """The fixed order the logs are learned in: start time, then name."""
    return sorted(logs, key=lambda s: (s.start_ns, s.name))


def learn(logs: Sequence[LogSteps], weights: dict[str, Any] | None = None, init: StoredTable | None = None,
          learning: dict[str, Any] | None = None) -> Learned:
    """The fleet's table from ``logs`` (any order). ``weights``/``learning``: reward weights and
    learning settings that override the fleet profile's; ``init``: a table to continue from."""
    refused = {s.name: s.error for s in logs if s.error is not None}
    ordered = order([s for s in logs if s.error is None])
    if not ordered:
        return Learned(None, (), 0, refused)
    reference = ordered[0]
    controller = learner(profile_with(reference.profile, weights, learning))
    layout, target = controller.layout(), controller.config.reward
    if init is not None:
        init.restore_into(controller.table, layout, reference.profile["name"])
    used, transitions = [], 0
    for log in ordered:
        why = _refusal(log, reference, layout, target)
        if why is not None:
            refused[log.name] = why
            continue
        transitions += _replay_steps(controller, log, target)
        used.append(log.name)
    table = controller.table
    info = {"profile": reference.profile["name"], "policy": "learn",
            "fleet": {"logs": used, "transitions": transitions, "merge": MERGE}}
    stored = StoredTable(table_meta(table, layout, info), table.q.copy(), table.visits.copy(), "fleet")
    return Learned(stored, tuple(used), transitions, dict(sorted(refused.items())))


def profile_with(profile: dict[str, Any], weights: dict[str, Any] | None,
                  learning: dict[str, Any] | None) -> dict[str, Any]:
    controller = dict(profile["controller"])
    if weights:
        controller["reward"] = {**controller["reward"], **weights}
    if learning:
        controller["learning"] = {**controller["learning"], **learning}
    return {**profile, "controller": controller}


def _refusal(log: LogSteps, reference: LogSteps, layout: dict[str, Any], target: RewardWeights) -> str | None:
    """Why ``log`` cannot be learned from into ``layout`` with ``target`` rewards; None when it can."""
    why = mismatch({"fingerprint": log.fingerprint, "layout": log.layout, "profile": log.profile["name"]}, layout,
                   reference.profile["name"])
    if why is not None:
        return f"another layout than {reference.name}'s: {why}"
    recorded = RewardWeights.model_validate(log.profile["controller"]["reward"])
    has_motion = "motion" in layout["states"]["factors"]
    cannot = unredoable(recorded, target, has_motion)
    if cannot:
        return "its reward weights differ and cannot be redone from its logged terms (a replay is needed): " + \
            "; ".join(f"reward.{k}: {v}" for k, v in cannot.items())
    factored = layout["actions"].get("blocks") is not None
    if factored and target.credit == "per-sensor" and log.steps and log.steps[-1].credit is None:
        return "per-sensor credit, but its decisions hold no per-sensor rewards (recorded before they were logged)"
    return None


def _replay_steps(controller: Any, log: LogSteps, target: RewardWeights) -> int:
    """``log``'s transitions through ``controller``'s learner; how many."""
    recorded = RewardWeights.model_validate(log.profile["controller"]["reward"])
    paid = rewards(log.steps, recorded, target)
    per_sensor = target.credit == "per-sensor"
    for previous, step, reward in zip(log.steps, log.steps[1:], paid[1:], strict=False):
        credit = list(step.credit) if per_sensor and step.credit is not None else None
        controller.learn(previous.state, previous.action, reward, step.state, credit)
    return max(len(log.steps) - 1, 0)
