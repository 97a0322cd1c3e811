"""The reward: r = α·clip(ConfAgg_t − ConfAgg_{t−1}, −κ, κ) − β·P_t − γ·L_t − δ·[switch].

Every term is returned so that each decision's log line shows why it was good or bad.
P is the board power from the rails when readable, else the profile's per-sensor power
model over what the drivers really applied. The switch indicator is "the configuration
changed": in product mode that is exactly [a_t ≠ a_{t−1}]; in moves mode repeating "thermal
rate up" is a switch while "keep" is not, which is what costs the sensors a re-arm.
An optional ``confidence_level`` term (default 0, the paper's reward) adds the ConfAgg level.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping

from respecd.control.config import RewardWeights
from respecd.drivers.base import SensorPower
from respecd.messages import SensorConfig


def sensor_power(configs: Iterable[tuple[str, SensorConfig]], models: Mapping[str, SensorPower]) -> float:
    """Watts of the sensors by the profile's power model; (sensor name, applied config) pairs."""
    return sum(models[name].watts(config) for name, config in configs if name in models)


def reward_terms(
    weights: RewardWeights,
    conf_prev: float | None,
    conf_now: float,
    power_w: float,
    latency_s: float,
    switched: bool,
) -> dict[str, float]:
    """Each weighted term and their sum under ``reward`` (the first step has no quality change)."""
    change = 0.0 if conf_prev is None else conf_now - conf_prev
    quality = weights.alpha * min(max(change, -weights.kappa), weights.kappa)
    terms = {
        "quality": quality,
        "level": weights.confidence_level * conf_now,
        "power": -weights.beta * power_w,
        "latency": -weights.gamma * latency_s,
        "switch": -weights.delta if switched else 0.0,
    }
    terms["reward"] = sum(terms.values())
    terms["power_w"] = power_w
    terms["latency_s"] = latency_s
    terms["conf_agg"] = conf_now
    return terms
