"""The reward: r = α·clip(ConfAgg_t − ConfAgg_{t−1}, −κ, κ) + λ·ConfAgg_t − β·P_t − γ·L_t − σ_m·D_t − η·B_t
− δ·[switch].

Every term is returned so that each decision's log line shows why it was good or bad.
P is the board power from the rails when readable, else the profile's per-sensor power
model over what the drivers really applied plus the detector's compute power (``compute_w``
× its busy share): on the rover the rails see the GPU, so a model without it would let the
agent keep the detector running flat out for free. The switch indicator is "the configuration
changed": in product and factored mode that is exactly [a_t ≠ a_{t−1}]; in moves mode repeating "thermal
rate up" is a switch while "keep" is not, which is what costs the sensors a re-arm.

Quality enters as the ConfAgg level λ (``confidence_level``, default 0.8), not the paper's
change α (``alpha``, default 0). With discount g, α·(C_t − C_{t−1}) = α(1−g)·C_t + [g·αC_t −
αC_{t−1}], and the bracket is potential-based shaping (Ng, Harada & Russell 1999), which does
not change the optimal policy when C is a function of the state; λ = α(1−g) = 4 × 0.2 keeps
the paper's incentive. The change form is noisier (two windows' noise, ×α instead of ×λ:
about 7× the standard deviation) and, since the table's state does not hold C_{t−1}, pays a
switch up to a richer configuration in one state and charges the switch back in another.

D is the sensing delay: the mean age of a scene change when its first frame is taken, half a
frame period, averaged over the detector's inputs by their contribution (``delay: contribution``)
or the slowest input's (``delay: slowest``). Its weight σ_m
depends on the motion bin: ConfAgg cannot see staleness (a detector is as sure of where a
person *was* as of where they are), so without this term nothing pays for a fast rate and
the compute term alone drives every sensor to 1 Hz, however fast the scene moves.

B is the sensing bandwidth in MB/s (``respecd.control.bandwidth``: the bytes the running
configuration makes the sensors produce), η its weight (``bandwidth``) — the paper's future
work. Power alone prices the depth camera, which the detector does not read, at 1.2 W plus
0.04 W per Hz: nearly free, though at 30 Hz it writes 18 MB/s.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence

from respecd.control.bandwidth import sensor_bandwidth
from respecd.control.config import RewardWeights
from respecd.messages import SensorConfig
from respecd.sensors import SensorPower

DETECTOR_MODALITIES = ("rgb", "thermal", "radar", "depth")  # inputs whose staleness the detector inherits


def sensor_power(configs: Iterable[tuple[str, SensorConfig]], models: Mapping[str, SensorPower]) -> float:
    """Watts of the sensors by the profile's power model; (sensor name, applied config) pairs."""
    return sum(models[name].watts(config) for name, config in configs if name in models)


def sensor_costs(weights: RewardWeights, configs: Iterable[tuple[str, SensorConfig]],
                 models: Mapping[str, SensorPower], radar_points: float | None) -> list[float]:
    """Each sensor's own share of the reward's cost terms, in order: −β·(its model watts) − η·(its MB/s)."""
    return [-weights.beta * sensor_power([(name, config)], models)
            - weights.bandwidth * (sensor_bandwidth(config, radar_points) / 1e6) for name, config in configs]


def per_sensor_rewards(reward: float, costs: Sequence[float], read: Sequence[bool],
                       follows: Sequence[int | None] | None = None) -> list[float]:
    """Per-sensor credit (``reward.credit: per-sensor``): each sensor's reward is the whole reward with
    the other sensors' costs taken out, and a sensor the detector does not read (``read`` False) gets its
    own costs alone — quality, staleness and latency do not depend on it, so they are only noise to it.
    ``follows``: per sensor, the sensor whose rate it runs at (``actions.shared_rate``) or None; a leader
    also pays its followers' costs, since its rate sets theirs."""
    shared = reward - sum(costs)
    own = list(costs)
    for i, leader in enumerate(follows or ()):
        if leader is not None:
            own[leader] += costs[i]
    return [shared + mine if reads else cost for cost, mine, reads in zip(costs, own, read, strict=True)]


def compute_power(busy: float, compute_w: float) -> float:
    """Watts the detector draws: ``busy`` is inference seconds per second (may exceed 1 when
    the configuration asks for more inferences than one accelerator can run)."""
    return compute_w * max(busy, 0.0)


def sensing_delay(configs: Iterable[SensorConfig], contributions: Mapping[str, float] | None) -> float:
    """Half the frame period of each running detector input, weighted by its contribution
    (equally while no attribution has run); 0 when no input runs."""
    periods = {c.modality: 0.5 / c.rate_hz for c in configs
               if c.enabled and c.rate_hz > 0 and c.modality in DETECTOR_MODALITIES}
    if not periods:
        return 0.0
    weights = {m: max((contributions or {}).get(m, 0.0), 0.0) for m in periods}
    total = sum(weights.values())
    if total <= 0.0:
        weights, total = dict.fromkeys(periods, 1.0), float(len(periods))
    return sum(periods[m] * w for m, w in weights.items()) / total


def slowest_delay(configs: Iterable[SensorConfig], inputs: Iterable[str]) -> float:
    """Half the frame period of the slowest running input among ``inputs`` (the modalities the
    detector reads); 0 when none runs. The detector fuses every frame it gets, so a stale frame
    of a modality it barely credits still pulls its boxes back to where people were
    (``reward.delay: slowest``; docs/CONTROLLER.md "Reward")."""
    read = set(inputs)
    return max((0.5 / c.rate_hz for c in configs if c.enabled and c.rate_hz > 0 and c.modality in read), default=0.0)


def quality_signal(weights: RewardWeights, conf_agg: float, truth_quality: float | None) -> float:
    """What the quality terms read: ConfAgg, or with ``quality: truth`` the window's F1 against the
    simulator's ground truth where a trainer supplies it. ConfAgg is the mean of the top scores, so a
    person the detector misses leaves it unchanged: it cannot tell the agent what a smaller RGB frame costs."""
    if weights.quality == "truth" and truth_quality is not None:
        return truth_quality
    return conf_agg


def reward_terms(
    weights: RewardWeights,
    conf_prev: float | None,
    conf_now: float,
    power_w: float,
    latency_s: float,
    switched: bool,
    delay_s: float = 0.0,
    motion_bin: int = 0,
    bandwidth_bps: float = 0.0,
) -> dict[str, float]:
    """Each weighted term and their sum under ``reward`` (the first step has no quality change).
    ``delay_s``: the sensing delay; ``motion_bin``: 0 still, 1 slow, 2 fast; ``bandwidth_bps``:
    the sensing bandwidth, bytes per second."""
    change = 0.0 if conf_prev is None else conf_now - conf_prev
    quality = weights.alpha * min(max(change, -weights.kappa), weights.kappa)
    terms = {
        "quality": quality,
        "conf_level": weights.confidence_level * conf_now,
        "power": -weights.beta * power_w,
        "latency": -weights.gamma * latency_s,
        "staleness": -weights.staleness[motion_bin] * delay_s,
        "bandwidth": -weights.bandwidth * bandwidth_bps / 1e6,
        "switch": -weights.delta if switched else 0.0,
    }
    terms["reward"] = sum(terms.values())
    terms["power_w"] = power_w
    terms["latency_s"] = latency_s
    terms["delay_s"] = delay_s
    terms["bandwidth_mb_s"] = bandwidth_bps / 1e6
    terms["conf_agg"] = conf_now
    return terms
