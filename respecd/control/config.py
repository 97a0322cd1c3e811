"""Profile section ``controller:``.

Every weight and threshold of the ReSPEC controller lives here so that a profile, not the
code, decides how the robot trades detection quality for power and latency. Thresholds are
pairs ``[low, high]``: a value below ``low`` is bin 0, below ``high`` bin 1, else bin 2.
"""

from __future__ import annotations

from typing import Literal

from pydantic import Field, field_validator, model_validator

from respecd.messages import RadarMode, Resolution
from respecd.sensors import MAX_RATE_HZ, MIN_RATE_HZ, StrictModel

Policy = Literal["learn", "exploit", "static", "heuristic"]
ActionMode = Literal["moves", "product", "factored"]
Factor = Literal["illumination", "motion", "radar_density", "load", "sync", "confidence"]
ControlledModality = Literal["rgb", "thermal", "radar", "depth"]

ALL_FACTORS: tuple[Factor, ...] = ("illumination", "motion", "radar_density", "load", "sync", "confidence")


class Thresholds(StrictModel):
    """Bin edges of the six state factors (value < low: bin 0; < high: bin 1; else bin 2)."""

    illumination: tuple[float, float] = Field(
        (0.2, 0.35),
        description="Mean RGB luminance 0..1, normalised to a 1/30 s exposure at gain 1 when the frame reports "
        "its exposure: dark / dim / bright.",
    )
    motion_image: tuple[float, float] = Field(
        (5.0, 12.0),
        description="Image motion score (p99 / median block change between consecutive frames; ~3.5-4 for a "
        "static scene): still / slow / fast.",
    )
    motion_imu_rad_s: tuple[float, float] = Field(
        (0.1, 0.5), description="Mean gyroscope rate norm (rad/s) when an IMU is present: still / slow / fast."
    )
    radar_points: tuple[float, float] = Field(
        (4.0, 20.0), description="Mean radar points per frame: sparse / medium / dense."
    )
    load: tuple[float, float] = Field(
        (0.5, 0.85),
        description="System load 0..1, the max of CPU share, GPU share and latency / latency_budget_s: "
        "low / medium / high.",
    )
    sync: tuple[float, float] = Field(
        (0.5, 1.5), description="Mean synchronizer health over the window, good=0 fair=1 poor=2: good / fair / poor."
    )
    confidence: tuple[float, float] = Field(
        (0.3, 0.6), description="Mean ConfAgg over the window (tau_l, tau_h): low / medium / high."
    )

    @model_validator(mode="after")
    def _ordered(self) -> Thresholds:
        for name in type(self).model_fields:
            low, high = getattr(self, name)
            if low > high:
                raise ValueError(f"{name}: low threshold {low:g} exceeds high threshold {high:g}")
        return self


class RewardWeights(StrictModel):
    """r = alpha*clip(dConfAgg, -kappa, kappa) + confidence_level*ConfAgg - beta*P - gamma*L
    - staleness[motion]*D - bandwidth*B - delta*[switch].

    P includes the detector's compute; D is the contribution-weighted sensing delay; B the
    sensing bandwidth in MB/s.
    """

    alpha: float = Field(
        0.0,
        ge=0,
        le=1000,
        description="Weight of the ConfAgg change (the paper's quality gain; the paper's reward: 4 with "
        "confidence_level 0). Default 0: the level term below carries the same incentive with less noise.",
    )
    kappa: float = Field(0.25, gt=0, le=1, description="Clip of the ConfAgg change per decision.")
    beta: float = Field(0.05, ge=0, le=1000, description="Weight of power, per watt.")
    compute_w: float = Field(
        7.0,
        ge=0,
        le=1000,
        description="Watts the detector's accelerator draws while busy (Jetson Orin Nano GPU about 7 W). Without "
        "power rails P adds compute_w x the detector's busy share (inference seconds per second); with rails the "
        "measured board power already holds it.",
    )
    gamma: float = Field(1.0, ge=0, le=1000, description="Weight of latency, per second of mean perception latency.")
    delta: float = Field(0.05, ge=0, le=1000, description="Penalty of a configuration switch (the sensors re-arm).")
    bandwidth: float = Field(
        0.01,
        ge=0,
        le=1000,
        description="Weight per MB/s of sensing bandwidth: the bytes per second the running configuration makes the "
        "sensors produce (raw pixels, radar UART packets, IMU samples; respecd.control.bandwidth). 0.01 prices "
        "1 MB/s like 0.2 W at beta 0.05: RGB 1280x720 at 30 Hz (83 MB/s) costs 0.83 a decision, the depth camera "
        "at 640x480 and 30 Hz (18 MB/s) 0.18, at 1 Hz 0.006. 0: bytes are free (the paper's reward).",
    )
    staleness: tuple[float, float, float] = Field(
        (0.0, 2.0, 4.0),
        description="Weight per second of sensing delay, by motion bin still / slow / fast. Sensing delay is how "
        "old a scene change is, on average, when its first frame is taken (half the frame period), averaged over "
        "the detector's inputs by their contribution (or the slowest input's, see delay): a slow sensor costs in "
        "proportion to how fast the scene moves and how much the detector relies on it. (0, 0, 0) is the paper's "
        "reward.",
    )
    delay: Literal["contribution", "slowest"] = Field(
        "contribution",
        description="How the sensing delay D combines the detector's inputs. contribution: their half frame "
        "periods weighted by contribution. slowest: the slowest input's half period - the detector fuses every "
        "frame it gets, and a stale frame of a modality it barely credits still costs accuracy on moving people "
        "(docs/CONTROLLER.md, Reward).",
    )
    quality: Literal["confagg", "truth"] = Field(
        "confagg",
        description="What the quality terms (alpha, confidence_level) read. confagg: the detector's own ConfAgg, the "
        "paper's and all a robot has. truth: training in the simulator only - the F1 at IoU 0.5 of the boxes the "
        "daemon would deliver against the simulator's ground truth, which counts the people the detector missed "
        "(ConfAgg, the mean of the top scores, cannot: docs/RESULTS.md, What limits the agent). Where no truth comes "
        "(the daemon, replay) ConfAgg is read.",
    )
    confidence_level: float = Field(
        0.8,
        ge=0,
        le=1000,
        description="Weight of the ConfAgg level. alpha x (C_t - C_t-1) equals alpha x (1 - discount) x C_t plus a "
        "potential-based shaping term that leaves the optimal policy unchanged, so 0.8 = 4 x (1 - 0.8) is the "
        "paper's alpha = 4 as a level; its per-decision noise is about 7x smaller and it gives nothing for a "
        "switch up that the switch back down takes away. 0 with alpha > 0: the paper's reward.",
    )

    credit: Literal["shared", "per-sensor"] = Field(
        "shared",
        description="Factored tables: the reward each sensor's block of columns learns from. shared: the whole "
        "reward, every block the same. per-sensor: each sensor pays its own power and bandwidth instead of "
        "everyone's, and a sensor the detector does not read (perception.model's inputs) learns from its own costs "
        "alone, since nothing else in the reward depends on it (difference rewards for independent learners). "
        "Product and moves tables always learn from the whole reward.",
    )
    unread: Literal["bootstrap", "immediate"] = Field(
        "bootstrap",
        description="Per-sensor credit: how the block of a sensor the detector does not read learns. bootstrap: as "
        "every block, its reward plus the discounted best value of the next state. immediate: its reward alone "
        "(discount 0). Its reward is its own costs, which depend on its own setting only, and its setting does not "
        "change what the detector sees, so its cheapest setting is the best in every state; bootstrapping adds only "
        "the next state's estimation noise - an optimistic, barely tried state is worth 1.0 where depth's costs "
        "differ by about 0.1 between 1 and 15 Hz (docs/CONTROLLER.md, Per-sensor credit).",
    )

    @model_validator(mode="after")
    def _staleness_non_negative(self) -> RewardWeights:
        if min(self.staleness) < 0 or max(self.staleness) > 1000:
            raise ValueError(f"staleness weights must lie in 0..1000, got {list(self.staleness)}")
        return self


class Learning(StrictModel):
    """Watkins Q-learning hyper-parameters."""

    learning_rate: float = Field(0.2, gt=0, le=1, description="Step size of the Q update (its floor with "
                                 "step_size 'visits').")
    step_size: Literal["visits", "constant"] = Field(
        "visits",
        description="visits: a cell's n-th update uses max(learning_rate, 1/n), so its first update replaces the "
        "initial value and its first 1/learning_rate updates are averaged; constant: learning_rate always. With "
        "optimistic init and a constant step, a cell updated twice still holds (1 - learning_rate)^2 of the "
        "optimistic value, and a frozen table prefers the actions it tried least.",
    )
    discount: float = Field(0.8, ge=0, lt=1, description="Discount of the next state's best value.")
    epsilon_start: float = Field(0.5, ge=0, le=1, description="Exploration probability at the first step.")
    epsilon_min: float = Field(0.05, ge=0, le=1, description="Floor the decay stops at.")
    epsilon_decay: float = Field(0.995, gt=0, le=1, description="Factor applied to epsilon after each learning step.")
    epsilon_exploit: float = Field(0.0, ge=0, le=1, description="Exploration in exploit mode (0 = purely greedy).")
    exploit_unseen: Literal["nearest", "hold"] = Field(
        "nearest",
        description="Exploit in a state the table never learned in: act as in the nearest learned state (fewest "
        "bins apart, the most visited among equals), or hold the current configuration.",
    )
    exploit_min_visits: int = Field(
        5,
        ge=1,
        le=1_000_000,
        description="Exploit treats a state with fewer updates than this as never learned in (see exploit_unseen): "
        "a row updated once or twice holds a reward sample or two, not a value.",
    )
    init: Literal["zero", "optimistic"] = Field(
        "optimistic", description="Initial Q-values: zero, or optimistic (tries every action before settling)."
    )
    optimistic_value: float = Field(1.0, ge=0, le=1000, description="Initial Q-value with init 'optimistic'.")

    @model_validator(mode="after")
    def _epsilon_order(self) -> Learning:
        if self.epsilon_min > self.epsilon_start:
            raise ValueError("epsilon_min must not exceed epsilon_start")
        return self


class ActionSpaceConfig(StrictModel):
    """The settings each controlled modality can take (cheapest first)."""

    mode: ActionMode = Field(
        "factored",
        description="moves: keep, or raise/lower one sensor's rate or setting (small, learns online); "
        "product: every action a full configuration (grows multiplicatively); "
        "factored: a full configuration chosen sensor by sensor, one Q-table block per sensor (grows additively).",
    )
    modalities: tuple[ControlledModality, ...] = Field(
        ("rgb", "thermal", "radar", "depth"), description="Modalities the controller re-configures (when present)."
    )
    rate_levels_hz: tuple[float, ...] = Field(
        (1.0, 5.0, 10.0, 15.0, 30.0),
        min_length=1,
        description="Sampling-rate levels (Hz), clamped per sensor to its capabilities and the sync cap; floor 1 Hz.",
    )
    rgb_resolutions: tuple[Resolution, ...] = Field(
        ((640, 360), (960, 540), (1280, 720)), min_length=1, description="RGB resolutions (paper), cheapest first."
    )
    thermal_resolutions: tuple[Resolution, ...] = Field(
        ((160, 120), (320, 240)), min_length=1, description="Thermal resolutions (paper), cheapest first."
    )
    radar_modes: tuple[RadarMode, ...] = Field(
        ("velocity", "range"), min_length=1, description="Radar chirp preferences the agent may pick."
    )
    depth_resolutions: tuple[Resolution, ...] = Field(
        (), description="Depth resolutions; empty keeps the sensor's configured resolution (rate moves only)."
    )
    max_actions: int = Field(4096, ge=1, le=1_000_000, description="Refuse a product space larger than this.")
    shared_rate: tuple[ControlledModality, ...] = Field(
        (),
        description="Modalities that run at one rate, the first present one's (the others choose their setting "
        "only, each clamped to what it can do). The detector runs on every new frame of its fastest input, so "
        "a slower input beside a faster one saves bytes but not load. Learning policies only; the baselines "
        "keep their own rates. Empty: every sensor chooses its own rate.",
    )

    @model_validator(mode="after")
    def _rates_in_range(self) -> ActionSpaceConfig:
        bad = [r for r in self.rate_levels_hz if not MIN_RATE_HZ <= r <= MAX_RATE_HZ]
        if bad:
            raise ValueError(f"rate levels must lie in {MIN_RATE_HZ:g}..{MAX_RATE_HZ:g} Hz, got {bad}")
        return self

    @model_validator(mode="after")
    def _shared_rate_is_controlled(self) -> ActionSpaceConfig:
        stray = [m for m in self.shared_rate if m not in self.modalities]
        if stray:
            raise ValueError(f"shared_rate: {', '.join(stray)} not among the controlled modalities "
                             f"({', '.join(self.modalities)})")
        if len(set(self.shared_rate)) != len(self.shared_rate):
            raise ValueError("shared_rate: a modality is listed twice")
        return self


class HeuristicRules(StrictModel):
    """What the heuristic policy adds to the documented rules (respecd/control/baselines.py).
    The defaults are the documented rules alone."""

    unread_floor: bool = Field(
        False,
        description="Sensors the detector does not read (not among perception.model's inputs, e.g. depth) at their "
        "cheapest setting and lowest rate: nothing the detector sees depends on them.",
    )
    radar_follows_cameras: bool = Field(
        False,
        description="The radar no faster than the fastest camera the rules chose, unless it is the dominant "
        "modality at low confidence: the detector runs on every new frame of any input, so a radar at 15 Hz beside "
        "cameras at 1 Hz would run it 15 times a second.",
    )
    still_rate_hz: float | None = Field(
        None, ge=MIN_RATE_HZ, le=MAX_RATE_HZ,
        description="Rate of every sensor when the motion bin is still (the nearest rung); null: the second rung.",
    )
    fast_rate_hz: float | None = Field(
        None, ge=MIN_RATE_HZ, le=MAX_RATE_HZ,
        description="Rate of every sensor when the motion bin is fast (the nearest rung); null: the top rung.",
    )
    bright_rgb: Resolution | None = Field(
        None, description="RGB resolution in bright light (the nearest of the ladder); null: the richest."
    )


class ControllerConfig(StrictModel):
    enabled: bool = Field(True, description="Run the controller task.")
    policy: Policy = Field("learn", description="learn (online Q-learning), exploit (frozen table), static, heuristic.")
    decision_period_s: float = Field(1.0, gt=0, le=60, description="Seconds between decisions.")
    window_s: float = Field(
        1.0, ge=0.25, le=10, description="Sliding window (s) the state factors are averaged over (paper: 0.5-1 s)."
    )
    min_dwell_s: float = Field(
        2.0, ge=0, le=600, description="Minimum seconds between two configuration switches (sensors are not thrashed)."
    )
    apply_timeout_s: float = Field(
        5.0, gt=0, le=120, description="Timeout (s) of one driver's apply (the radar restarts its chirp)."
    )
    contribution: Literal["dominant", "none"] = Field(
        "dominant", description="How contribution scores enter the state: the dominant modality, or not at all."
    )
    factors: tuple[Factor, ...] = Field(
        ALL_FACTORS, min_length=1, description="State factors used (default: the paper's six)."
    )
    latency_budget_s: float = Field(
        0.2, gt=0, le=10, description="Perception latency (s) that counts as full load in the load factor."
    )
    system_probe: bool = Field(
        True,
        description="Read CPU/GPU load and power rails (off: load from perception latency only, deterministic replay).",
    )
    seed: int = Field(0, ge=0, description="Seed of the exploration random generator.")
    save_every: int = Field(
        30, ge=1, le=100_000, description="Save the Q-table every N learning updates (and on stop)."
    )
    warm_start: bool = Field(
        True,
        description="learn: with no table of its own in the state directory, start from the shipped table when it "
        "was learned for this layout (its epsilon), not from an empty one at epsilon_start.",
    )
    table_file: str = Field(
        "", description="Q-table file name in the state directory; empty: qtable-<profile name>.npz."
    )
    thresholds: Thresholds = Field(Thresholds(), description="Bin edges of the state factors.")
    reward: RewardWeights = Field(RewardWeights(), description="Reward weights.")
    learning: Learning = Field(Learning(), description="Q-learning hyper-parameters.")
    actions: ActionSpaceConfig = Field(ActionSpaceConfig(), description="Action space.")
    heuristic: HeuristicRules = Field(HeuristicRules(), description="Rules of the heuristic policy beyond the "
                                      "documented ones (default: none).")

    @field_validator("table_file")
    @classmethod
    def _inside_state_dir(cls, name: str) -> str:
        """A file name, not a path: the Q-table lives in the state directory and nowhere else."""
        if name and (name in (".", "..") or any(c in name for c in "/\\\0")):
            raise ValueError(f"must be a file name inside the state directory (no '/' or '..'), got {name!r}")
        return name

    @model_validator(mode="after")
    def _unique_factors(self) -> ControllerConfig:
        if len(set(self.factors)) != len(self.factors):
            raise ValueError("factors must not repeat")
        return self
