"""Rewards of logged decisions under other weights, from the terms the controller logged.

A decision's reward is ``reward_terms`` of raw signals it also logged (ConfAgg, power, latency,
sensing delay, bandwidth, whether it switched): under new weights the same function gives the
reward the robot would have been paid — exact, no replay. Some weights cannot be redone so:

* ``compute_w``: the logged power already holds the detector's compute at the old weight, and
  its busy share is not logged;
* ``delay``, ``credit``, ``unread``: they change what the delay or each sensor's reward is made
  of, not how much it weighs;
* ``delta`` when the log's was 0 (a switch left no trace in its term), ``staleness`` when
  motion is not a state factor (the motion bin is not logged).

For those a replay is needed (``fleet eval --profile`` with the weights changed).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from respecd.control.config import RewardWeights
from respecd.control.reward import reward_terms
from respecd.lab.fleet.transitions import Step

NEED_A_REPLAY = {
    "compute_w": "the logged power holds the detector's compute at the recorded weight; its busy share is not logged",
    "delay": "it changes what the sensing delay is made of, which the log holds only as one number",
    "credit": "per-sensor rewards are made of each sensor's own costs, which the log does not hold",
    "unread": "it changes how a sensor's block learns, not a weight of the logged terms",
}


def unredoable(old: RewardWeights, new: RewardWeights, has_motion: bool) -> dict[str, str]:
    """The weights that changed and cannot be redone from the logged terms, and why."""
    changed = {k for k in type(new).model_fields if getattr(old, k) != getattr(new, k)}
    why = {k: NEED_A_REPLAY[k] for k in sorted(changed & NEED_A_REPLAY.keys())}
    if "delta" in changed and old.delta == 0:
        why["delta"] = "the log's switch penalty was 0, so its terms do not say when it switched"
    if changed and new.credit == "per-sensor":
        why["credit"] = "per-sensor rewards are logged at the recorded weights, made of costs the log does not hold"
    if "staleness" in changed and not has_motion and len(set(old.staleness)) > 1:
        why["staleness"] = "motion is not a state factor, so the log does not say which motion weight applied"
    return why


def rewards(steps: Sequence[Step], old: RewardWeights, new: RewardWeights) -> list[float]:
    """Each step's reward under ``new`` (the logged one where nothing changed, bit for bit)."""
    if old == new:
        return [s.reward for s in steps]
    out = []
    for i, step in enumerate(steps):
        t = step.terms
        previous = steps[i - 1].terms.get("conf_agg") if i else None
        switched = t.get("switch", 0.0) < 0.0
        motion = step.motion if step.motion is not None else _motion_of(t, old)
        redone = reward_terms(new, previous, t["conf_agg"], t["power_w"], t["latency_s"], switched, t["delay_s"],
                              motion, t["bandwidth_mb_s"] * 1e6)
        out.append(redone["reward"])
    return out


def _motion_of(terms: dict[str, float], old: RewardWeights) -> int:
    """The motion bin whose staleness weight explains the logged staleness term (0 when all are equal)."""
    delay = terms.get("delay_s", 0.0)
    if delay <= 0:
        return 0
    weight = -terms.get("staleness", 0.0) / delay
    return min(range(3), key=lambda m: abs(old.staleness[m] - weight))


def with_overrides(weights: RewardWeights, overrides: dict[str, Any]) -> RewardWeights:
    """``weights`` with ``overrides`` (validated: a bad value is a ConfigError from pydantic's message)."""
    return RewardWeights.model_validate({**weights.model_dump(), **overrides})
