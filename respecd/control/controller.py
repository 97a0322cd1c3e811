"""The decision step, without asyncio: observation in, ``Decision`` out.

``Controller.step(observation)`` does, in order: bin the state; compute the reward
of the previous action (ConfAgg change, power, latency, switch); in ``learn`` mode apply
the Watkins update to the previous (state, action); choose the next action (ε-greedy,
greedy in ``exploit``, or a baseline's target); hold it if the minimum dwell time since the
last switch has not passed. It is deterministic for a given seed and sequence of
observations. ``follow(applied)`` tells it what the sensors really run (the control loop
calls it on every configuration message), so a clamped or failed apply moves it back.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

from respecd.control.actions import ActionSpace, Position, build_slots
from respecd.control.bandwidth import sensing_bandwidth
from respecd.control.baselines import heuristic_position, static_position
from respecd.control.config import ALL_FACTORS, ControllerConfig, RewardWeights
from respecd.control.learned import LearnedStates
from respecd.control.qlearning import FactoredQTable, QTable
from respecd.control.reward import (
    DETECTOR_MODALITIES,
    compute_power,
    per_sensor_rewards,
    quality_signal,
    reward_terms,
    sensing_delay,
    sensor_costs,
    sensor_power,
    slowest_delay,
)
from respecd.control.state import Observation, StateSpace, motion_bin
from respecd.messages import Decision, SensorConfig
from respecd.sensors import Capabilities, SensorPower

if TYPE_CHECKING:
    from respecd.config import Profile

LEARNING_POLICIES = ("learn", "exploit")


class Controller:
    """State, reward, Q-table and action choice for one run (pure, seedable)."""

    def __init__(
        self,
        config: ControllerConfig,
        space: ActionSpace,
        states: StateSpace,
        powers: Mapping[str, SensorPower] | None = None,
        position: Position | None = None,
        detector_inputs: tuple[str, ...] = DETECTOR_MODALITIES,
    ) -> None:
        self.config = config
        self.detector_inputs = detector_inputs  # modalities the detector reads (per-sensor credit)
        self.policy = config.policy
        self.space = space
        # per action slot: does the detector read it (per-sensor credit and reward.unread act on this)
        self._read = [slot.modality in detector_inputs for slot in space.slots]
        self._immediate = _immediate_blocks(config.reward, self._read)
        self.states = states
        self.powers = dict(powers or {})
        self.position: Position = position if position is not None else space.maximum()
        self.table: QTable | None = None
        if self.policy in LEARNING_POLICIES:
            self.table = _make_table(states.size, space, config)
        self._prev_state: int | None = None
        self._prev_action = 0
        self._prev_conf: float | None = None
        self._switched = False
        self._last_switch_t = -math.inf
        self._model_cache: tuple[Position, float] | None = None
        self._applied: Mapping[str, SensorConfig] | None = None
        self._applied_changed = False
        self._applied_power: float | None = None
        self._learned: LearnedStates | None = None
        # learn on a table that was loaded (the shipped one or the robot's own): act on what it learned and
        # explore at epsilon only; optimism (an untried action's value) is for a table learned from nothing
        self.refining = False

    @classmethod
    def from_profile(
        cls, config: ControllerConfig, profile: Profile, capabilities: Mapping[str, Capabilities] | None = None
    ) -> Controller:
        """Build the spaces from the profile's sensors (and the drivers' capabilities)."""
        # like ``factors``, the tied rates shape the learner's actions; the baselines keep their own rates
        shared = config.actions.shared_rate if config.policy in LEARNING_POLICIES else ()
        slots = build_slots(config.actions, profile.sensors, capabilities, profile.sync.max_rate_hz, shared)
        space = ActionSpace(slots, config.actions.mode, config.actions.max_actions)
        modalities: list[str] = []
        for slot in slots:
            if slot.modality not in modalities:
                modalities.append(slot.modality)
        contributions = modalities if config.contribution == "dominant" else []
        # the heuristic's rules read all six bins: ``factors`` shapes the learner's state, not the baseline
        factors = config.factors if config.policy in LEARNING_POLICIES else ALL_FACTORS
        states = StateSpace(factors, config.thresholds, contributions)
        powers = {s.name: s.power for s in profile.sensors}
        inputs = ("rgb", *profile.perception.model.aux_modalities)
        return cls(config, space, states, powers, detector_inputs=inputs)

    @property
    def epsilon(self) -> float:
        if self.policy == "learn" and self.table is not None:
            return self.table.epsilon
        return self.config.learning.epsilon_exploit if self.policy == "exploit" else 0.0

    def layout(self) -> dict[str, Any]:
        """The state/action layout a saved table must match (and that ``policy show`` prints):
        a name per table column, and in factored mode the column blocks (one per sensor)."""
        actions: dict[str, Any] = {"space": self.space.fingerprint_data(), "names": self.space.descriptions()}
        if self.space.mode == "factored":
            actions["blocks"] = list(self.space.blocks)
        return {"states": self.states.fingerprint_data(), "actions": actions}

    def describe_action(self, action: int) -> str:
        if self.policy in LEARNING_POLICIES:
            return self.space.describe(action)
        return self.space.describe_position(self.space.position_of(action))

    def follow(self, applied: Mapping[str, SensorConfig]) -> None:
        """What each sensor (by name) really runs changed: the next step starts from it."""
        self._applied = applied
        self._applied_changed = True

    def step(self, obs: Observation) -> Decision:
        """One decision from the window's observation."""
        applied = self._applied
        if applied and self._applied_changed:
            self._applied_changed = False
            self._applied_power = None
            self.position = self._resync(applied)
        bins = self.states.bins(obs)
        state = self.states.index(bins)
        power = obs.power_w
        if power is None:  # no rails: the sensors' model plus the detector's compute
            power = self._model_power(applied) + compute_power(obs.busy, self.config.reward.compute_w)
        running = tuple(applied.values()) if applied else self.space.requests(self.position)
        if self.config.reward.delay == "slowest":
            delay = slowest_delay(running, self.detector_inputs)
        else:
            delay = sensing_delay(running, obs.contributions)
        motion = motion_bin(obs, self.states.thresholds)
        bandwidth = sensing_bandwidth(running, obs.radar_points)
        quality = quality_signal(self.config.reward, obs.conf_agg, obs.truth_quality)
        terms = reward_terms(self.config.reward, self._prev_conf, quality, power, obs.latency_s, self._switched,
                             delay, motion, bandwidth)
        if obs.truth_quality is not None:  # a trainer's: the log line keeps it beside the detector's own
            terms["truth_quality"], terms["conf_agg"] = obs.truth_quality, obs.conf_agg
        reward = terms["reward"]
        if self.policy == "learn" and self.table is not None and self._prev_state is not None:
            factored = isinstance(self.table, FactoredQTable)
            blocks = self._block_rewards(reward, applied, obs.radar_points) if factored else None
            if blocks is not None:  # recorded with the decision: a fleet learns from it without a replay
                terms.update({f"credit.{slot.name}": r for slot, r in zip(self.space.slots, blocks, strict=True)})
            terms["td_error"] = self.learn(self._prev_state, self._prev_action, reward, state, blocks)
        action, target = self._choose(state, bins)
        if target != self.position and obs.t - self._last_switch_t < self.config.min_dwell_s:
            action, target = self.space.hold_action(self.position), self.position  # dwell: keep sensors settled
            terms["held"] = 1.0
        self._switched = target != self.position
        if self._switched:
            self._last_switch_t = obs.t
        self.position = target
        self._prev_state, self._prev_action, self._prev_conf = state, action, quality
        q_values = tuple(self.table.q[state].tolist()) if self.table is not None else ()
        return Decision(
            t=obs.t,
            state=bins,
            action=action,
            reward=reward,
            epsilon=self.epsilon,
            q_values=q_values,
            configs=self.space.requests(target),
            terms=terms,
        )

    def learn(self, state: int, action: int, reward: float, next_state: int,
              block_rewards: list[float] | None = None) -> float:
        """The Q-update of one transition, as ``step`` makes it in learn mode (``fleet learn`` replays
        the transitions logs recorded through it); the TD error."""
        assert self.table is not None
        if isinstance(self.table, FactoredQTable):
            error = self.table.update(state, action, reward, next_state, block_rewards, self._immediate)
        else:
            error = self.table.update(state, action, reward, next_state)
        if self._learned is not None:  # the learned states change only when this one just became learned
            became = self.table.updates_of(state) == self.config.learning.exploit_min_visits
            self._learned = None if became else self._learned.at(self.table.updates)
        return error

    def _block_rewards(self, reward: float, applied: Mapping[str, SensorConfig] | None,
                       radar_points: float | None) -> list[float] | None:
        """Each sensor's (block's) reward under per-sensor credit; None: the shared reward for all."""
        if self.config.reward.credit != "per-sensor":
            return None
        requested = self.space.requests(self.position)
        configs = [(slot.name, applied.get(slot.name, req) if applied else req)
                   for slot, req in zip(self.space.slots, requested, strict=True)]
        costs = sensor_costs(self.config.reward, configs, self.powers, radar_points)
        return per_sensor_rewards(reward, costs, self._read, self.space.follows)

    def _choose(self, state: int, bins: tuple[int, ...]) -> tuple[int, Position]:
        if self.policy == "static":
            target = static_position(self.space)
            return self.space.config_id(target), target
        if self.policy == "heuristic":
            target = heuristic_position(self.space, self.states.names(bins), self.config.heuristic,
                                        self.detector_inputs)
            return self.space.config_id(target), target
        assert self.table is not None
        if self.policy == "exploit":
            return self._exploit(state)
        if self.refining:
            return self._refine(state)
        action = self.table.choose(state, self.epsilon)
        return action, self.space.apply(self.position, action)

    def _refine(self, state: int) -> tuple[int, Position]:
        """Learn on a loaded table: the best learned action, each sensor (block) explored with probability
        epsilon. The optimistic value of an action the table never tried would otherwise beat every
        learned one, and a warm-started robot would run its sensors at whatever it tried least."""
        assert self.table is not None
        action, _ = self._best_learned(state)
        epsilon, rng = self.epsilon, self.table.rng
        if isinstance(self.table, FactoredQTable):
            cells = [int(rng.integers(size)) if epsilon > 0.0 and rng.random() < epsilon else cell
                     for cell, size in zip(self.table.cells(action), self.table.blocks, strict=True)]
            action = self.table.encode(cells)
        elif epsilon > 0.0 and rng.random() < epsilon:
            return self._random_action()
        return action, self.space.apply(self.position, action)

    def _exploit(self, state: int) -> tuple[int, Position]:
        """``_best_learned``, or with probability ``epsilon_exploit`` a random action."""
        assert self.table is not None
        epsilon = self.config.learning.epsilon_exploit
        if epsilon > 0.0 and self.table.rng.random() < epsilon:
            return self._random_action()
        return self._best_learned(state)

    def _random_action(self) -> tuple[int, Position]:
        """Any action of the space, drawn with the table's generator (exploration stays seeded)."""
        assert self.table is not None
        action = int(self.table.rng.integers(self.space.n))
        return action, self.space.apply(self.position, action)

    def _best_learned(self, state: int) -> tuple[int, Position]:
        """Best learned action; in a state never learned in (fewer than ``exploit_min_visits``
        updates), that of the nearest learned state (``exploit_unseen: nearest``) or hold."""
        assert self.table is not None
        learned = self._learned_states()
        action = self.table.greedy_tried(state) if state in learned else None
        if action is None and self.config.learning.exploit_unseen == "nearest":
            stand_in = learned.nearest(state)
            action = None if stand_in is None else self.table.greedy_tried(stand_in)
        if action is None:
            return self.space.hold_action(self.position), self.position
        return action, self.space.apply(self.position, action)

    def _learned_states(self) -> LearnedStates:
        """Rebuilt only when the table changed (a frozen table: once, after it is loaded)."""
        assert self.table is not None
        if self._learned is None or self._learned.version != self.table.updates:
            self._learned = LearnedStates(self.table, self.states, self.config.learning.exploit_min_visits)
        return self._learned

    def _resync(self, applied: Mapping[str, SensorConfig]) -> Position:
        """Follow what the drivers really run (a failed or clamped apply moves us back)."""
        cells = list(self.position)
        for i, slot in enumerate(self.space.slots):
            if slot.name in applied:
                cells[i] = slot.nearest(applied[slot.name])
        return self.space.tied(tuple(cells))

    def _model_power(self, applied: Mapping[str, SensorConfig] | None) -> float:
        if applied:
            if self._applied_power is None:
                self._applied_power = sensor_power(applied.items(), self.powers)
            return self._applied_power
        if self._model_cache is None or self._model_cache[0] != self.position:
            names = (slot.name for slot in self.space.slots)
            watts = sensor_power(zip(names, self.space.requests(self.position), strict=True), self.powers)
            self._model_cache = (self.position, watts)
        return self._model_cache[1]


def _immediate_blocks(weights: RewardWeights, read: list[bool]) -> list[bool] | None:
    """Blocks that learn their reward alone: with per-sensor credit and ``reward.unread: immediate``,
    those of the sensors the detector does not read; None: every block bootstraps."""
    if weights.credit != "per-sensor" or weights.unread != "immediate":
        return None
    return [not r for r in read]


def _make_table(n_states: int, space: ActionSpace, config: ControllerConfig) -> QTable:
    if space.mode == "factored":
        return FactoredQTable(n_states, space.blocks, config.learning, config.seed)
    return QTable(n_states, space.n, config.learning, config.seed)
