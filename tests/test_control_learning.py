"""Reward terms, the Watkins update, epsilon decay, and learn mode on a toy problem."""

from __future__ import annotations

import numpy as np
import pytest

from respecd.control.actions import ActionSpace, Slot
from respecd.control.config import ControllerConfig, Learning, RewardWeights, Thresholds
from respecd.control.controller import Controller
from respecd.control.qlearning import FactoredQTable, QTable
from respecd.control.reward import quality_signal, reward_terms, sensing_delay, sensor_power, slowest_delay
from respecd.control.state import Observation, StateSpace
from respecd.messages import SensorConfig
from respecd.sensors import SensorPower


def test_reward_terms_hand_computed() -> None:
    w = RewardWeights(alpha=2.0, confidence_level=0.0, kappa=0.1, beta=0.5, gamma=3.0, delta=0.25)
    terms = reward_terms(w, conf_prev=0.2, conf_now=0.25, power_w=4.0, latency_s=0.1, switched=True)
    assert terms["quality"] == pytest.approx(2.0 * 0.05)
    assert terms["power"] == pytest.approx(-2.0)
    assert terms["latency"] == pytest.approx(-0.3)
    assert terms["switch"] == pytest.approx(-0.25)
    assert terms["reward"] == pytest.approx(0.1 - 2.0 - 0.3 - 0.25)
    clipped = reward_terms(w, conf_prev=0.9, conf_now=0.1, power_w=0.0, latency_s=0.0, switched=False)
    assert clipped["quality"] == pytest.approx(-0.2)  # clip(-0.8, -0.1, 0.1) * 2
    assert clipped["switch"] == 0.0
    first = reward_terms(w, conf_prev=None, conf_now=0.7, power_w=0.0, latency_s=0.0, switched=False)
    assert first["quality"] == 0.0 and first["conf_agg"] == 0.7


def test_power_model_per_resolution_and_rate() -> None:
    models = {
        "cam": SensorPower(static_w=0.5, per_hz_w={"1280x720": 0.05, "default": 0.02}),
        "radar": SensorPower(static_w=1.0, per_hz_w={"range": 0.01}),
    }
    configs = [
        ("cam", SensorConfig("rgb", rate_hz=10.0, resolution=(1280, 720))),
        ("radar", SensorConfig("radar", rate_hz=20.0, mode="range")),
        ("unknown", SensorConfig("depth", rate_hz=30.0)),
    ]
    assert sensor_power(configs, models) == pytest.approx(0.5 + 0.5 + 1.0 + 0.2)
    cheap = [("cam", SensorConfig("rgb", rate_hz=10.0, resolution=(640, 360)))]
    assert sensor_power(cheap, models) == pytest.approx(0.5 + 0.2)


def test_watkins_update_hand_computed() -> None:
    table = QTable(3, 2, Learning(learning_rate=0.5, discount=0.9, init="zero", step_size="constant"))
    table.q[1] = [0.0, 2.0]
    error = table.update(0, 1, reward=1.0, next_state=1)
    # Q(0,1) = 0 + 0.5 * (1 + 0.9 * max(0, 2) - 0) = 1.4
    assert error == pytest.approx(2.8)
    assert table.q[0, 1] == pytest.approx(1.4)
    table.update(0, 1, reward=-1.0, next_state=2)
    # Q(0,1) = 1.4 + 0.5 * (-1 + 0.9 * 0 - 1.4) = 0.2
    assert table.q[0, 1] == pytest.approx(0.2)
    assert table.visits[0].tolist() == [0, 2] and table.updates == 2


def test_epsilon_decays_geometrically_to_the_floor() -> None:
    table = QTable(1, 2, Learning(epsilon_start=0.5, epsilon_decay=0.9, epsilon_min=0.2))
    seen = []
    for _ in range(12):
        table.update(0, 0, 0.0, 0)
        seen.append(table.epsilon)
    assert seen[0] == pytest.approx(0.45)
    assert seen[1] == pytest.approx(0.405)
    assert seen[-1] == pytest.approx(0.2)
    assert all(a >= b for a, b in zip(seen, seen[1:], strict=False))


def test_greedy_breaks_ties_at_random_but_seeded() -> None:
    picks = [QTable(1, 4, Learning(init="zero"), seed=s).greedy(0) for s in range(20)]
    assert len(set(picks)) > 1
    again = [QTable(1, 4, Learning(init="zero"), seed=s).greedy(0) for s in range(20)]
    assert picks == again
    table = QTable(1, 4, Learning(init="zero"))
    table.q[0, 2] = 0.1
    assert {table.choose(0, epsilon=0.0) for _ in range(20)} == {2}
    assert len({table.choose(0, epsilon=1.0) for _ in range(200)}) == 4


def _toy(seed: int, **learning: float) -> Controller:
    """Two states (dark/bright) x two actions (thermal 160x120 or 320x240)."""
    config = ControllerConfig(
        factors=("illumination",), contribution="none", min_dwell_s=0.0, seed=seed,
        reward=RewardWeights(alpha=0.0, confidence_level=1.0, beta=0.0, gamma=0.0, delta=0.0),
        learning=Learning(learning_rate=0.3, discount=0.5, epsilon_start=1.0, epsilon_decay=0.99,
                          epsilon_min=0.05, init="zero", **learning),
    )
    slot = Slot("flir", "thermal", ((160, 120), (320, 240)), (9.0,))
    space = ActionSpace((slot,), "product")
    states = StateSpace(config.factors, Thresholds(), ())
    return Controller(config, space, states)


def test_learn_mode_converges_on_a_two_state_toy_problem() -> None:
    # In the dark the 320x240 thermal setting (action 1) pays; in bright light 160x120 does.
    rng = np.random.default_rng(7)
    controller = _toy(seed=3)
    light = 0.1
    conf = 0.5
    for step in range(400):
        decision = controller.step(Observation(t=float(step), n_percepts=1, illumination=light, conf_agg=conf))
        best = 1 if light < 0.25 else 0
        conf = 0.9 if decision.action == best else 0.1  # what the next window will observe
        light = float(rng.choice([0.1, 0.8]))
    table = controller.table
    dark, bright = 0, 2  # illumination bins
    assert table.q[dark].argmax() == 1 and table.q[bright].argmax() == 0
    assert table.q[dark, 1] > table.q[dark, 0] + 0.3
    assert table.epsilon == pytest.approx(0.05)
    greedy = {s: table.greedy(s) for s in (dark, bright)}
    assert greedy == {dark: 1, bright: 0}


def test_exploit_mode_does_not_update_and_static_never_learns() -> None:
    controller = _toy(seed=1)
    controller.policy = "exploit"
    before = controller.table.q.copy()
    for step in range(20):
        controller.step(Observation(t=float(step), n_percepts=1, illumination=0.1, conf_agg=step / 20))
    assert np.array_equal(before, controller.table.q)
    assert controller.epsilon == 0.0


def test_dwell_time_holds_switches() -> None:
    controller = _toy(seed=0)
    controller.config = controller.config.model_copy(update={"min_dwell_s": 5.0})
    positions, held = [], 0
    for step in range(30):
        decision = controller.step(Observation(t=float(step), n_percepts=1, illumination=0.5, conf_agg=0.5))
        positions.append(controller.position)
        held += int(decision.terms.get("held", 0))
    switches = [t for t in range(1, 30) if positions[t] != positions[t - 1]]
    assert held > 0
    assert all(b - a >= 5 for a, b in zip(switches, switches[1:], strict=False))


def test_wide_rows_take_the_numpy_path_with_the_same_semantics() -> None:
    table = QTable(2, 500, Learning(init="zero", learning_rate=1.0, discount=0.5), seed=4)
    table.q[1, 321] = 2.0
    assert table.greedy(1) == 321
    table.update(0, 7, reward=1.0, next_state=1)
    assert table.q[0, 7] == pytest.approx(1.0 + 0.5 * 2.0)
    assert len({QTable(1, 500, Learning(init="zero"), seed=s).greedy(0) for s in range(10)}) > 1


def test_exploit_acts_on_tried_actions_and_holds_where_nothing_was_learned() -> None:
    controller = _toy(seed=2)
    controller.config = controller.config.model_copy(update={"learning": controller.config.learning.model_copy(
        update={"init": "optimistic", "exploit_unseen": "hold", "exploit_min_visits": 1})})
    table = controller.table
    table.q[:] = 1.0  # optimistic
    table.q[0] = [0.2, -0.4]  # dark: both tried, action 0 learned better
    table.visits[0] = [3, 2]
    table.q[2, 0] = -0.1  # bright: only action 0 tried, action 1 still at its optimistic 1.0
    table.visits[2, 0] = 1
    controller.policy = "exploit"
    picks = {}
    for step, light in enumerate((0.1, 0.8, 0.3)):
        decision = controller.step(Observation(t=float(step), n_percepts=1, illumination=light, conf_agg=0.5))
        picks[light] = (decision.action, controller.position)
    assert picks[0.1][0] == 0 and picks[0.8][0] == 0  # never the untried optimistic action
    assert picks[0.3][1] == picks[0.8][1]  # dim: never learned in, the configuration is held


@pytest.mark.parametrize(("unseen", "dim_setting"), [("nearest", 1), ("hold", 0)])
def test_exploit_in_an_unseen_state_acts_as_the_nearest_learned_one(unseen: str, dim_setting: int) -> None:
    controller = _toy(seed=2, exploit_unseen=unseen, exploit_min_visits=1)  # type: ignore[arg-type]
    table = controller.table
    table.q[0] = [-0.4, 0.2]  # dark: 320x240 learned better, 5 visits
    table.visits[0] = [2, 3]
    table.q[2] = [0.1, -0.3]  # bright: 160x120, 2 visits
    table.visits[2] = [1, 1]
    controller.policy = "exploit"
    for step, light in enumerate((0.8, 0.3)):  # bright, then dim (never learned in)
        controller.step(Observation(t=float(step), n_percepts=1, illumination=light, conf_agg=0.5))
    # dim is one bin from dark and from bright; nearest takes the more visited, dark
    assert controller.position == ((dim_setting, 0),)


def test_exploit_treats_a_barely_learned_state_as_unseen() -> None:
    controller = _toy(seed=2, exploit_min_visits=4)  # type: ignore[arg-type]
    table = controller.table
    table.q[0] = [-0.4, 0.2]  # dark: 320x240 learned better over 5 updates
    table.visits[0] = [2, 3]
    table.q[1] = [0.3, -0.3]  # dim: 160x120 after 2 updates, too few to act on
    table.visits[1] = [1, 1]
    table.q[2] = [0.1, -0.3]  # bright: 160x120 over 4 updates
    table.visits[2] = [2, 2]
    controller.policy = "exploit"
    controller.position = ((0, 0),)  # 160x120: neither holding nor dim's own row would leave it
    controller.step(Observation(t=0.0, n_percepts=1, illumination=0.3, conf_agg=0.5))  # dim
    # dark and bright are one bin from dim; dark has more updates
    assert controller.position == ((1, 0),)


def test_state_distances_count_ordinal_bins_and_a_changed_dominant_modality() -> None:
    states = StateSpace(("illumination", "motion"), Thresholds(), ("rgb", "thermal"))
    others = np.array([[0, 0, 1], [2, 0, 1], [0, 1, 2], [1, 2, 0]])
    # from dark/still/rgb: itself 0, bright 2 bins, slow + thermal 1 + 1, dim + fast + none 1 + 2 + 1
    assert states.distances((0, 0, 1), others).tolist() == [0, 2, 2, 4]


def test_detector_compute_enters_the_modelled_power_but_not_measured_rails() -> None:
    # The rails see the accelerator; the per-sensor model does not, so without rails the
    # controller adds compute_w x the detector's busy share.
    config = ControllerConfig(factors=("illumination",), contribution="none", min_dwell_s=0.0,
                              reward=RewardWeights(compute_w=8.0), learning=Learning(init="zero"))
    slot = Slot("cam", "rgb", ((640, 360),), (5.0,))
    powers = {"cam": SensorPower(static_w=1.0, per_hz_w={"default": 0.0})}
    controller = Controller(config, ActionSpace((slot,), "product"), StateSpace(config.factors, Thresholds()), powers)
    controller.follow({"cam": SensorConfig("rgb", rate_hz=5.0, resolution=(640, 360))})
    modelled = controller.step(Observation(t=0.0, n_percepts=5, busy=0.25))
    assert modelled.terms["power_w"] == pytest.approx(1.0 + 8.0 * 0.25)
    idle = controller.step(Observation(t=1.0, n_percepts=0, busy=0.0))
    assert idle.terms["power_w"] == pytest.approx(1.0)
    rails = controller.step(Observation(t=2.0, n_percepts=5, busy=0.25, power_w=6.5))
    assert rails.terms["power_w"] == pytest.approx(6.5)


def test_sensing_delay_weights_each_input_by_its_contribution() -> None:
    rgb = SensorConfig("rgb", rate_hz=1.0, resolution=(640, 360))
    thermal = SensorConfig("thermal", rate_hz=10.0, resolution=(160, 120))
    imu = SensorConfig("imu", rate_hz=200.0)
    off = SensorConfig("radar", enabled=False, rate_hz=30.0)
    # half a frame period each: rgb 0.5 s, thermal 0.05 s; the IMU and a disabled radar do not count
    delay = sensing_delay([rgb, thermal, imu, off], {"rgb": 0.2, "thermal": 0.8})
    assert delay == pytest.approx(0.2 * 0.5 + 0.8 * 0.05)
    assert sensing_delay([rgb, thermal], None) == pytest.approx((0.5 + 0.05) / 2)  # before any attribution
    assert sensing_delay([rgb, thermal], {"radar": 1.0}) == pytest.approx((0.5 + 0.05) / 2)
    assert sensing_delay([imu], {"rgb": 1.0}) == 0.0


def test_staleness_costs_by_motion_bin() -> None:
    w = RewardWeights(staleness=(0.0, 1.0, 3.0))
    base = {"conf_prev": 0.5, "conf_now": 0.5, "power_w": 0.0, "latency_s": 0.0, "switched": False, "delay_s": 0.2}
    assert reward_terms(w, **base, motion_bin=0)["staleness"] == 0.0
    assert reward_terms(w, **base, motion_bin=1)["staleness"] == pytest.approx(-0.2)
    fast = reward_terms(w, **base, motion_bin=2)
    assert fast["staleness"] == pytest.approx(-0.6) and fast["reward"] == pytest.approx(-0.6 + 0.8 * 0.5)
    assert fast["delay_s"] == 0.2
    with pytest.raises(ValueError, match="staleness"):
        RewardWeights(staleness=(0.0, -1.0, 1.0))


def test_controller_charges_a_slow_camera_only_when_the_scene_moves() -> None:
    config = ControllerConfig(factors=("motion",), contribution="none", min_dwell_s=0.0,
                              reward=RewardWeights(staleness=(0.0, 2.0, 4.0)), learning=Learning(init="zero"))
    slot = Slot("cam", "rgb", ((640, 360),), (1.0,))
    controller = Controller(config, ActionSpace((slot,), "product"), StateSpace(config.factors, Thresholds()))
    controller.follow({"cam": SensorConfig("rgb", rate_hz=1.0, resolution=(640, 360))})
    still = controller.step(Observation(t=0.0, n_percepts=1, motion_image=3.5))
    fast = controller.step(Observation(t=1.0, n_percepts=1, motion_image=20.0))
    assert still.terms["staleness"] == 0.0
    assert fast.terms["staleness"] == pytest.approx(-4.0 * 0.5)


@pytest.mark.parametrize(("delay", "expected"), [("contribution", 0.9 * 0.5 / 9 + 0.1 * 0.5), ("slowest", 0.5)])
def test_controller_delay_weights_the_stale_camera_by_its_contribution_or_fully(delay: str, expected: float) -> None:
    reward = RewardWeights(staleness=(0.0, 2.0, 4.0), delay=delay)
    config = ControllerConfig(factors=("motion",), contribution="none", min_dwell_s=0.0, reward=reward,
                              learning=Learning(init="zero"))
    slots = (Slot("cam", "rgb", ((640, 360),), (1.0,)), Slot("ir", "thermal", ((160, 120),), (9.0,)))
    controller = Controller(config, ActionSpace(slots, "product"), StateSpace(config.factors, Thresholds()),
                            detector_inputs=("rgb", "thermal"))
    controller.follow({"cam": SensorConfig("rgb", rate_hz=1.0, resolution=(640, 360)),
                       "ir": SensorConfig("thermal", rate_hz=9.0, resolution=(160, 120))})
    fast = controller.step(Observation(t=0.0, n_percepts=1, motion_image=20.0,
                                       contributions={"rgb": 0.1, "thermal": 0.9}))
    assert fast.terms["delay_s"] == pytest.approx(expected)
    assert fast.terms["staleness"] == pytest.approx(-4.0 * expected)


def test_default_reward_is_the_papers_change_term_as_a_level() -> None:
    """alpha x (C_t - C_t-1) = alpha (1 - discount) C_t + discount x alpha C_t - alpha C_t-1: the default
    charges the level with the weight that leaves the same optimal policy, and nothing for the change."""
    weights, discount = RewardWeights(), Learning().discount
    assert weights.alpha == 0.0 and weights.confidence_level == pytest.approx(4.0 * (1 - discount))
    up = reward_terms(weights, conf_prev=0.2, conf_now=0.7, power_w=0.0, latency_s=0.0, switched=False)
    same = reward_terms(weights, conf_prev=0.7, conf_now=0.7, power_w=0.0, latency_s=0.0, switched=False)
    assert up["quality"] == 0.0 and up["reward"] == same["reward"] == pytest.approx(0.8 * 0.7)


def test_truth_quality_replaces_confagg_only_where_a_trainer_supplies_it() -> None:
    truth = RewardWeights(quality="truth")
    assert quality_signal(RewardWeights(), 0.9, 0.4) == 0.9  # the default reads ConfAgg whatever comes
    assert quality_signal(truth, 0.9, 0.4) == 0.4
    assert quality_signal(truth, 0.9, None) == 0.9  # the daemon and replay: no truth
    config = ControllerConfig(factors=("motion",), contribution="none", min_dwell_s=0.0, reward=truth,
                              learning=Learning(init="zero"))
    controller = Controller(config, ActionSpace((Slot("cam", "rgb", ((640, 360),), (1.0,)),), "product"),
                            StateSpace(config.factors, Thresholds()))
    trained = controller.step(Observation(t=0.0, n_percepts=1, conf_agg=0.9, truth_quality=0.4))
    assert trained.terms["conf_level"] == pytest.approx(0.8 * 0.4)
    assert trained.terms["conf_agg"] == 0.9 and trained.terms["truth_quality"] == 0.4
    daemon = controller.step(Observation(t=1.0, n_percepts=1, conf_agg=0.9))
    assert daemon.terms["conf_level"] == pytest.approx(0.8 * 0.9) and "truth_quality" not in daemon.terms


def test_reward_terms_do_not_shadow_log_record_keys() -> None:
    # every term goes into the `decision` log line as a keyword: a term named like one of
    # structlog's own keys would be silently overwritten there
    terms = reward_terms(RewardWeights(confidence_level=1.0), 0.2, 0.5, 3.0, 0.1, True, 0.2, 2)
    assert not set(terms) & {"event", "level", "timestamp", "logger", "state", "action", "epsilon"}
    assert terms["conf_level"] == pytest.approx(0.5)


def test_visit_step_size_averages_the_first_targets_then_floors_at_the_learning_rate() -> None:
    table = QTable(1, 1, Learning(learning_rate=0.25, discount=0.0, init="optimistic", optimistic_value=1.0))
    targets = [-1.0, -0.5, 0.0, -0.3, 2.0]
    for reward in targets:
        table.update(0, 0, reward, next_state=0)  # discount 0: the target is the reward
    mean_of_four = sum(targets[:4]) / 4  # steps 1, 1/2, 1/3, 1/4: the optimistic 1.0 is gone after the first
    assert table.q[0, 0] == pytest.approx(mean_of_four + 0.25 * (2.0 - mean_of_four))  # then the 0.25 floor


@pytest.mark.parametrize(("step_size", "picked"), [("visits", 0), ("constant", 1)])
def test_frozen_table_prefers_what_it_learned_not_what_it_tried_least(step_size: str, picked: int) -> None:
    """With an optimistic start and a constant step, a cell tried once keeps 80 % of its
    optimistic value and outbids a cell learned over twenty updates; counting visits does not."""
    table = QTable(1, 2, Learning(learning_rate=0.2, discount=0.0, step_size=step_size))  # optimistic 1.0
    for _ in range(20):
        table.update(0, 0, reward=-0.1, next_state=0)
    table.update(0, 1, reward=-0.3, next_state=0)  # worse, and tried once
    assert table.greedy_tried(0) == picked


def test_factored_update_moves_each_blocks_chosen_cell() -> None:
    from respecd.control.qlearning import FactoredQTable

    table = FactoredQTable(2, (3, 2), Learning(learning_rate=0.5, discount=0.9, init="zero", step_size="constant"))
    assert table.q.shape == (2, 5) and table.cells(table.encode([2, 1])) == [2, 1]
    assert table.greedy_tried(0) is None  # nothing learned in state 0 yet
    table.q[1] = [0.0, 4.0, 1.0, 2.0, -1.0]  # next state: block 0 best 4, block 1 best 2
    error = table.update(0, table.encode([1, 0]), reward=1.0, next_state=1)
    # block 0, cell 1: 0.5 * (1 + 0.9 * 4) = 2.3; block 1, cell 0: 0.5 * (1 + 0.9 * 2) = 1.4
    assert table.q[0].tolist() == pytest.approx([0.0, 2.3, 0.0, 1.4, 0.0])
    assert error == pytest.approx((4.6 + 2.8) / 2)
    assert table.visits[0].tolist() == [0, 1, 0, 1, 0] and table.updates == 1
    assert table.greedy_tried(0) == table.encode([1, 0])
    assert table.greedy(1) == table.encode([1, 0]) and table.choose(1, epsilon=0.0) == table.encode([1, 0])


def test_factored_exploration_is_per_block() -> None:
    from respecd.control.qlearning import FactoredQTable

    table = FactoredQTable(1, (4, 4), Learning(init="zero"), seed=3)
    table.q[0] = [5.0, 0, 0, 0, 5.0, 0, 0, 0]  # greedy: cell 0 in both blocks
    picks = [table.cells(table.choose(0, epsilon=0.5)) for _ in range(4000)]
    explored = [sum(cells[b] != 0 for cells in picks) / len(picks) for b in (0, 1)]
    # each block explores on its own: P(cell != greedy) = 0.5 * 3/4, both blocks independently
    assert explored == pytest.approx([0.375, 0.375], abs=0.03)
    both = sum(cells[0] != 0 and cells[1] != 0 for cells in picks) / len(picks)
    assert both == pytest.approx(0.375 ** 2, abs=0.03)


def test_sensing_bandwidth_counts_the_bytes_each_running_sensor_makes() -> None:
    from respecd.control.bandwidth import frame_bytes, sensing_bandwidth

    rgb = SensorConfig("rgb", rate_hz=10.0, resolution=(640, 360))
    depth = SensorConfig("depth", rate_hz=30.0, resolution=(640, 480))
    radar = SensorConfig("radar", rate_hz=10.0, mode="range")
    off = SensorConfig("thermal", enabled=False, rate_hz=9.0, resolution=(160, 120))
    assert frame_bytes(rgb) == 640 * 360 * 3 and frame_bytes(depth) == 640 * 480 * 2 and frame_bytes(off) == 0.0
    assert frame_bytes(radar, 10.0) - frame_bytes(radar, 0.0) == pytest.approx(10 * 20)  # 20 B per point
    total = sensing_bandwidth([rgb, depth, radar, off], radar_points=5.0)
    assert total == pytest.approx(640 * 360 * 3 * 10 + 640 * 480 * 2 * 30 + frame_bytes(radar, 5.0) * 10)


def test_controller_charges_the_bandwidth_its_configuration_makes() -> None:
    """The same scene, depth at 30 Hz or at 1 Hz: with a bandwidth weight the fast depth camera
    costs its 18.4 MB/s, without one both score the same."""
    from respecd.control.bandwidth import sensing_bandwidth

    def reward(weight: float, depth_hz: float) -> dict[str, float]:
        config = ControllerConfig(factors=("motion",), contribution="none", min_dwell_s=0.0,
                                  reward=RewardWeights(bandwidth=weight, beta=0.0), learning=Learning(init="zero"))
        slot = Slot("depth", "depth", ((640, 480),), (1.0, 30.0))
        controller = Controller(config, ActionSpace((slot,), "product"), StateSpace(config.factors, Thresholds()))
        controller.follow({"depth": SensorConfig("depth", rate_hz=depth_hz, resolution=(640, 480))})
        return controller.step(Observation(t=0.0, n_percepts=1, motion_image=3.5)).terms

    fast, slow = reward(0.01, 30.0), reward(0.01, 1.0)
    assert fast["bandwidth_mb_s"] == pytest.approx(640 * 480 * 2 * 30 / 1e6)
    assert fast["bandwidth"] == pytest.approx(-0.01 * 18.432) and slow["bandwidth"] == pytest.approx(-0.01 * 0.6144)
    assert fast["reward"] < slow["reward"]
    assert reward(0.0, 30.0)["reward"] == reward(0.0, 1.0)["reward"]
    depth = SensorConfig("depth", rate_hz=30.0, resolution=(640, 480))
    assert fast["bandwidth_mb_s"] == pytest.approx(sensing_bandwidth([depth]) / 1e6)


def _rgb_and_depth(credit: str, seed: int = 0, bandwidth: float = 0.01, learning: Learning | None = None,
                   unread: str = "bootstrap", depth_rates: tuple[float, ...] = (1.0, 30.0),
                   factors: tuple[str, ...] = ("illumination",)) -> Controller:
    """A factored table over a camera the detector reads and a depth camera it does not."""
    config = ControllerConfig(
        factors=factors, contribution="none", min_dwell_s=0.0, seed=seed,
        reward=RewardWeights(beta=0.05, bandwidth=bandwidth, delta=0.0, gamma=0.0, credit=credit, unread=unread),
        learning=learning or Learning(init="zero", discount=0.5, epsilon_start=1.0, epsilon_decay=0.99,
                                      epsilon_min=0.2),
    )
    slots = (Slot("cam", "rgb", ((640, 360),), (5.0,)), Slot("depth", "depth", ((640, 480),), depth_rates))
    powers = {"cam": SensorPower(static_w=1.0, per_hz_w={"default": 0.01}),
              "depth": SensorPower(static_w=1.2, per_hz_w={"default": 0.04})}
    return Controller(config, ActionSpace(slots, "factored"), StateSpace(config.factors, Thresholds()), powers,
                      detector_inputs=("rgb", "thermal", "radar"))


def test_per_sensor_rewards_take_out_the_other_sensors_costs() -> None:
    from respecd.control.reward import per_sensor_rewards

    # reward -1.0 holds the costs -0.3 (read) and -0.5 (not read): the first keeps its own, the second only its own
    assert per_sensor_rewards(-1.0, [-0.3, -0.5], [True, False]) == pytest.approx([-0.5, -0.5])
    assert per_sensor_rewards(0.4, [-0.1, -0.2], [True, True]) == pytest.approx([0.6, 0.5])
    # with shared_rate the first sensor's rate sets the second's: its block pays both costs
    assert per_sensor_rewards(0.4, [-0.1, -0.2], [True, True], [None, 0]) == pytest.approx([0.4, 0.5])


@pytest.mark.parametrize("credit", ["shared", "per-sensor"])
def test_each_block_learns_from_its_credit(credit: str) -> None:
    controller = _rgb_and_depth(credit)
    controller.follow({"cam": SensorConfig("rgb", rate_hz=5.0, resolution=(640, 360)),
                       "depth": SensorConfig("depth", rate_hz=30.0, resolution=(640, 480))})
    first = controller.step(Observation(t=0.0, n_percepts=1, illumination=0.8, conf_agg=0.5, busy=0.0))
    state, action = controller._prev_state, first.action
    second = controller.step(Observation(t=1.0, n_percepts=1, illumination=0.8, conf_agg=0.5, busy=0.0))
    depth_cost = -0.05 * (1.2 + 0.04 * 30) - 0.01 * 640 * 480 * 2 * 30 / 1e6
    cam_cell, depth_cell = controller.table.cells(action)  # type: ignore[union-attr]
    q = controller.table.q[state]  # type: ignore[union-attr]
    # zero init, first update of each cell: its value is the reward it was given (the next row is all 0)
    if credit == "shared":
        assert q[cam_cell] == pytest.approx(second.reward) and q[1 + depth_cell] == pytest.approx(second.reward)
    else:
        assert q[1 + depth_cell] == pytest.approx(depth_cost)
        assert q[cam_cell] == pytest.approx(second.reward - depth_cost)


def _learns_cheapest_depth_rate(credit: str, seed: int) -> bool:
    """150 decisions with power the only price (bandwidth free): does depth end at 1 Hz?"""
    rng = np.random.default_rng(seed)
    controller = _rgb_and_depth(credit, seed=seed, bandwidth=0.0)
    for step in range(150):  # confidence swings by +-0.4: x0.8, five times depth's 0.058 price difference
        decision = controller.step(Observation(t=float(step), n_percepts=1, illumination=0.8,
                                               conf_agg=float(rng.uniform(0.1, 0.9)), busy=0.0))
        controller.follow(dict(zip(("cam", "depth"), decision.configs, strict=True)))
    table = controller.table
    assert isinstance(table, FactoredQTable) and controller._prev_state is not None
    return table.cells(table.greedy(controller._prev_state))[1] == 0


@pytest.mark.slow
def test_a_sensor_the_detector_does_not_read_learns_its_cheapest_rate_through_quality_noise() -> None:
    per_sensor = [_learns_cheapest_depth_rate("per-sensor", seed) for seed in range(20)]
    shared = [_learns_cheapest_depth_rate("shared", seed) for seed in range(20)]
    assert all(per_sensor)
    assert not all(shared)  # with the whole reward, the noise of quality outvotes depth's price in some runs


def _depth_settles_on_its_cheapest_rate(unread: str, seed: int) -> bool:
    """The shipped learning settings (optimistic start, discount 0.8, ε 0.05), depth's five rates, and a scene that
    is mostly bright and confident, now and then one of five other states for a decision: after 300 decisions,
    does depth run at 1 Hz in the state it spent most of them in?"""
    rng = np.random.default_rng(seed)
    learning = Learning(init="optimistic", optimistic_value=1.0, discount=0.8, epsilon_start=0.05,
                        epsilon_min=0.05)
    controller = _rgb_and_depth("per-sensor", seed=seed, learning=learning, unread=unread,
                                depth_rates=(1.0, 5.0, 10.0, 15.0, 30.0), factors=("illumination", "confidence"))
    usual = Observation(t=0.0, n_percepts=1, illumination=0.8, conf_agg=0.9, busy=0.0)
    for step in range(300):
        light, conf = (float(rng.choice([0.1, 0.3, 0.8])), float(rng.choice([0.1, 0.5]))) if rng.random() < 0.1 \
            else (0.8, 0.9)
        decision = controller.step(Observation(t=float(step), n_percepts=1, illumination=light, conf_agg=conf,
                                               busy=0.0))
        controller.follow(dict(zip(("cam", "depth"), decision.configs, strict=True)))
    table = controller.table
    assert isinstance(table, FactoredQTable)
    return table.cells(table.greedy_tried(controller.states.index(controller.states.bins(usual))) or 0)[1] == 0


@pytest.mark.slow
def test_an_unread_sensor_learning_its_costs_alone_settles_on_its_cheapest_rate() -> None:
    # Depth's own costs rise by 0.033 a decision from 1 to 5 Hz. Bootstrapping, each cell's target holds the next
    # state's best value as it stood when the cell was last chosen: values fall from the optimistic 1.0 towards
    # about -0.34, so the cell tried longest ago looks best, and a first visit to a rare state lifts the cell
    # chosen before it by 0.8. Learning its costs alone, each cell holds its cost from its first update on.
    immediate = [_depth_settles_on_its_cheapest_rate("immediate", seed) for seed in range(20)]
    bootstrap = [_depth_settles_on_its_cheapest_rate("bootstrap", seed) for seed in range(20)]
    assert all(immediate)
    assert sum(bootstrap) <= 15


def test_immediate_blocks_learn_their_reward_alone() -> None:
    table = FactoredQTable(2, (2, 2), Learning(init="zero", discount=0.5, learning_rate=1.0, step_size="constant"))
    table.q[1] = [4.0, 0.0, 4.0, 0.0]
    table.update(0, table.encode([0, 1]), 0.0, 1, block_rewards=[-1.0, -1.0], immediate=[False, True])
    assert table.q[0].tolist() == pytest.approx([-1.0 + 0.5 * 4.0, 0.0, 0.0, -1.0])
    with pytest.raises(ValueError, match="immediate flags"):
        table.update(0, 0, 0.0, 1, immediate=[True])


def test_slowest_delay_is_the_slowest_detector_input_whatever_it_contributes() -> None:
    rgb = SensorConfig("rgb", rate_hz=1.0, resolution=(640, 360))
    thermal = SensorConfig("thermal", rate_hz=9.0, resolution=(160, 120))
    depth = SensorConfig("depth", rate_hz=0.5, resolution=(640, 480))  # not read by the detector
    off = SensorConfig("radar", enabled=False, rate_hz=0.2, mode="range")
    inputs = ("rgb", "thermal", "radar")
    assert slowest_delay([rgb, thermal, depth, off], inputs) == pytest.approx(0.5)
    assert slowest_delay([thermal], inputs) == pytest.approx(0.5 / 9)
    assert slowest_delay([depth, off], inputs) == 0.0
