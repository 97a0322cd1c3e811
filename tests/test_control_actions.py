"""Action space: sizes, moves, product ids, mapping to SensorConfig with clamping, baselines."""

from __future__ import annotations

import dataclasses

import pytest

from respecd.control.actions import ActionSpace, build_slots
from respecd.control.baselines import heuristic_position, static_position
from respecd.control.config import ActionSpaceConfig, HeuristicRules
from respecd.errors import ConfigError
from respecd.sensors import Capabilities, DriverConfigBase, clamp_request

# the FLIR One Pro: 160x120 native (320x240 upscaled), no more than ~9 Hz (SENSORS.md §3)
FLIR_CAPS = Capabilities("thermal", resolutions=((160, 120), (320, 240)), max_rate_hz=9.0, upscaled=((320, 240),))
UVC_CAPS = Capabilities("rgb", resolutions=((1280, 720), (640, 360)), max_rate_hz=30.0)


def _sensors() -> list[DriverConfigBase]:
    return [
        DriverConfigBase(driver="sim", name="cam", modality="rgb", resolution=(1280, 720)),
        DriverConfigBase(driver="sim", name="flir", modality="thermal", resolution=(160, 120), rate_hz=9),
        DriverConfigBase(driver="sim", name="radar", modality="radar", mode="range", rate_hz=10),
        DriverConfigBase(driver="sim", name="imu", modality="imu"),
    ]


def test_moves_space_is_small_and_each_move_changes_one_knob() -> None:
    slots = build_slots(ActionSpaceConfig(), _sensors(), sync_cap_hz=27.0)
    space = ActionSpace(slots, "moves")
    assert [s.name for s in slots] == ["cam", "flir", "radar"]  # the IMU is not controlled
    assert space.n == 1 + 3 * 4
    assert slots[0].rates == (1.0, 5.0, 10.0, 15.0, 27.0)  # the sync cap replaces 30 Hz
    start = ((1, 2), (0, 2), (0, 2))
    assert space.apply(start, 0) == start
    assert space.describe(2) == "cam rate up"
    assert space.apply(start, 2) == ((1, 3), (0, 2), (0, 2))
    assert space.describe(7) == "flir setting down"
    assert space.apply(start, 7) == start  # already the cheapest setting: a move past the end stays put
    top = space.maximum()
    assert space.apply(top, space.descriptions().index("radar rate up")) == top


def test_product_space_ids_round_trip_and_requests() -> None:
    config = ActionSpaceConfig(mode="product", rate_levels_hz=(1.0, 10.0))
    space = ActionSpace(build_slots(config, _sensors()), "product")
    assert space.n == (3 * 2) * (2 * 2) * (2 * 2)
    for action in range(space.n):
        assert space.config_id(space.apply(space.maximum(), action)) == action
    cam, flir, radar = space.requests(space.position_of(space.n - 1))
    assert (cam.resolution, cam.rate_hz, cam.enabled) == ((1280, 720), 10.0, True)
    assert (flir.resolution, flir.rate_hz) == ((320, 240), 10.0)
    assert (radar.mode, radar.resolution) == ("range", None)
    cam0, _, radar0 = space.requests(space.position_of(0))
    assert (cam0.resolution, cam0.rate_hz, radar0.mode) == ((640, 360), 1.0, "velocity")


def test_product_space_over_the_cap_is_a_config_error() -> None:
    slots = build_slots(ActionSpaceConfig(), _sensors())
    with pytest.raises(ConfigError, match="max_actions=100"):
        ActionSpace(slots, "product", max_actions=100)


def test_mapping_clamps_to_capabilities_like_the_driver_would() -> None:
    caps = {"flir": FLIR_CAPS, "cam": UVC_CAPS}
    slots = build_slots(ActionSpaceConfig(), _sensors(), caps, sync_cap_hz=30.0)
    cam, flir = slots[0], slots[1]
    assert flir.rates == (1.0, 5.0, 9.0)  # 10, 15, 30 Hz collapse onto the FLIR's 9 Hz
    assert cam.settings == ((640, 360), (1280, 720))  # 960x540 is not a mode this camera has
    space = ActionSpace(slots, "moves")
    for request, name in zip(space.requests(space.maximum()), ("cam", "flir", "radar"), strict=True):
        assert clamp_request(caps.get(name, Capabilities(request.modality, modes=("velocity", "range"))),
                             request).rate_hz == request.rate_hz
    # without capabilities, the driver's clamp is what reports the change
    blind = build_slots(ActionSpaceConfig(), _sensors())[1]
    applied = clamp_request(FLIR_CAPS, blind.request(1, len(blind.rates) - 1))
    assert applied.rate_hz == 9.0 and any("capped at 9" in n for n in applied.notes)
    assert any("upscaled" in n for n in applied.notes)
    assert blind.nearest(applied) == (1, 2)  # 9 Hz maps back to the 10 Hz rung


def test_rate_floor_is_one_hz() -> None:
    slots = build_slots(ActionSpaceConfig(rate_levels_hz=(1.0, 2.0)), _sensors(),
                        {"cam": Capabilities("rgb", resolutions=((640, 360),), min_rate_hz=5.0, max_rate_hz=15.0)})
    assert slots[0].rates == (5.0,)
    assert all(min(s.rates) >= 1.0 for s in slots)


def test_static_baseline_is_every_sensor_at_maximum() -> None:
    space = ActionSpace(build_slots(ActionSpaceConfig(), _sensors(), {"flir": FLIR_CAPS}), "moves")
    cam, flir, radar = space.requests(static_position(space))
    assert (cam.resolution, cam.rate_hz) == ((1280, 720), 30.0)
    assert (flir.resolution, flir.rate_hz) == ((320, 240), 9.0)
    assert (radar.mode, radar.rate_hz) == ("range", 30.0)


def _heuristic(space: ActionSpace, **names: str) -> dict:
    base = {"illumination": "dim", "motion": "slow", "radar_density": "medium", "load": "low",
            "sync": "good", "confidence": "medium", "dominant": "none"}
    requests = space.requests(heuristic_position(space, {**base, **names}))
    return {s.name: r for s, r in zip(space.slots, requests, strict=True)}


def test_heuristic_rules() -> None:
    space = ActionSpace(build_slots(ActionSpaceConfig(), _sensors()), "moves")
    dark = _heuristic(space, illumination="dark")
    bright = _heuristic(space, illumination="bright")
    assert dark["flir"].resolution == (320, 240) and dark["flir"].rate_hz > bright["flir"].rate_hz
    assert dark["cam"].resolution == (640, 360) and dark["cam"].rate_hz < bright["cam"].rate_hz
    assert bright["cam"].resolution == (1280, 720)
    fast, still = _heuristic(space, motion="fast"), _heuristic(space, motion="still")
    assert all(fast[n].rate_hz == 30.0 for n in fast)
    assert all(still[n].rate_hz <= 5.0 for n in still)
    assert _heuristic(space, radar_density="dense")["radar"].mode == "range"
    assert _heuristic(space, motion="fast")["radar"].mode == "velocity"
    low_conf = _heuristic(space, confidence="low", dominant="radar")["radar"]
    assert low_conf.rate_hz == 30.0
    loaded = _heuristic(space, load="high")
    assert loaded["cam"].resolution == (640, 360)
    assert all(loaded[n].rate_hz < _heuristic(space)[n].rate_hz for n in loaded)
    assert all(r.rate_hz >= 1.0 for r in _heuristic(space, illumination="dark", motion="still",
                                                     load="high").values())


def test_engineered_rules_floor_unread_sensors_and_keep_the_radar_at_the_cameras_rate() -> None:
    sensors = [*_sensors(), DriverConfigBase(driver="sim", name="depth", modality="depth", resolution=(640, 480))]
    space = ActionSpace(build_slots(ActionSpaceConfig(depth_resolutions=((424, 240), (640, 480))), sensors), "moves")
    tuned = HeuristicRules(unread_floor=True, radar_follows_cameras=True, still_rate_hz=1.0, fast_rate_hz=15.0,
                           bright_rgb=(960, 540))
    read = ("rgb", "thermal", "radar")

    def rules(rules: HeuristicRules, **names: str) -> dict:
        base = {"illumination": "bright", "motion": "still", "radar_density": "dense", "load": "low",
                "sync": "good", "confidence": "medium", "dominant": "none"}
        position = heuristic_position(space, {**base, **names}, rules, read)
        return {s.name: r for s, r in zip(space.slots, space.requests(position), strict=True)}

    old, new = rules(HeuristicRules()), rules(tuned)
    assert old["radar"].rate_hz == 30.0 and old["depth"].rate_hz == 5.0  # dense: the radar would set the rate
    assert new["radar"].rate_hz == new["cam"].rate_hz == 1.0 and new["radar"].mode == "range"
    assert (new["depth"].resolution, new["depth"].rate_hz) == ((424, 240), 1.0)  # not read: its floor
    assert new["cam"].resolution == (960, 540) and old["cam"].resolution == (1280, 720)
    fast = rules(tuned, motion="fast")
    assert fast["cam"].rate_hz == fast["flir"].rate_hz == 15.0 and fast["radar"].rate_hz <= 15.0
    leaning = rules(tuned, confidence="low", dominant="radar")
    assert leaning["radar"].rate_hz == 30.0  # the detector relies on the radar: it may run fast
    assert rules(tuned, illumination="dark")["radar"].rate_hz <= 1.0  # cameras at 1 Hz (still): the radar too
    assert rules(HeuristicRules(), illumination="dark") == _heuristic_with(space, read)  # the defaults change nothing


def _heuristic_with(space: ActionSpace, read: tuple[str, ...]) -> dict:
    names = {"illumination": "dark", "motion": "still", "radar_density": "dense", "load": "low", "sync": "good",
             "confidence": "medium", "dominant": "none"}
    return {s.name: r for s, r in zip(space.slots, space.requests(heuristic_position(space, names)), strict=True)}


async def test_mapping_through_the_real_flir_one_driver_clamps_and_reports() -> None:
    from respecd.clock import ManualClock
    from respecd.drivers.flirone import FlirOneConfig, FlirOneDriver

    flir = FlirOneDriver(FlirOneConfig(name="flir"), ManualClock())  # constructor does no I/O
    sensors = [DriverConfigBase(driver="sim", name="flir", modality="thermal", resolution=(160, 120), rate_hz=9)]
    fitted = ActionSpace(build_slots(ActionSpaceConfig(), sensors, {"flir": flir.capabilities}), "moves")
    assert fitted.slots[0].rates[-1] == 9.0  # the driver's cap became the top rung
    for position in (fitted.maximum(), ((0, 0),)):
        (request,) = fitted.requests(position)
        applied = await flir.apply(request)
        assert (applied.rate_hz, applied.resolution) == (request.rate_hz, request.resolution)
    blind = ActionSpace(build_slots(ActionSpaceConfig(), sensors), "moves")  # capabilities unknown
    (request,) = blind.requests(blind.maximum())
    applied = await flir.apply(request)
    assert request.rate_hz == 30.0 and applied.rate_hz == 9.0
    assert any("9 Hz" in note for note in applied.notes)
    assert blind.nearest({"flir": applied}) == ((1, 2),)  # what the controller then believes it runs


def test_factored_space_names_the_product_but_holds_one_block_per_sensor() -> None:
    config = ActionSpaceConfig(mode="factored", rate_levels_hz=(1.0, 10.0))
    space = ActionSpace(build_slots(config, _sensors()), "factored", max_actions=16)
    assert space.n == (3 * 2) * (2 * 2) * (2 * 2)  # action ids: whole positions, as in product mode
    assert space.blocks == (6, 4, 4) and space.columns == 14  # table columns: a block of cells per sensor
    names = space.descriptions()
    assert len(names) == 14 and names[:2] == ["cam 640x360@1Hz", "cam 640x360@10Hz"]
    assert names[6:] == ["flir 160x120@1Hz", "flir 160x120@10Hz", "flir 320x240@1Hz", "flir 320x240@10Hz",
                         "radar velocity@1Hz", "radar velocity@10Hz", "radar range@1Hz", "radar range@10Hz"]
    position = ((2, 0), (1, 1), (0, 1))
    action = space.config_id(position)
    assert space.apply(space.maximum(), action) == position and space.hold_action(position) == action
    assert space.describe(action) == "cam 1280x720@1Hz flir 320x240@10Hz radar velocity@10Hz"
    with pytest.raises(ConfigError, match="14 actions, more than max_actions=13"):
        ActionSpace(build_slots(config, _sensors()), "factored", max_actions=13)


def test_heuristic_reads_load_even_when_the_learner_leaves_it_out() -> None:
    """``factors`` shapes the learner's state; the baseline it is compared with must not change."""
    from respecd.config import load_profile
    from respecd.control.controller import Controller
    from respecd.control.state import Observation

    profile = load_profile("builtin:sim-rover")
    without_load = profile.controller.model_copy(
        update={"factors": ("illumination", "motion", "radar_density", "sync", "confidence")})
    learner = Controller.from_profile(without_load.model_copy(update={"policy": "learn"}), profile)
    assert "load" not in learner.states.factors
    chosen = {}
    for load in (0.1, 0.95):
        heuristic = Controller.from_profile(without_load.model_copy(update={"policy": "heuristic"}), profile)
        obs = Observation(t=10.0, n_percepts=5, illumination=0.5, motion_image=8.0, radar_points=10.0, load=load,
                          conf_agg=0.5)
        chosen[load] = heuristic.step(obs).configs
    rgb_low, rgb_high = chosen[0.1][0], chosen[0.95][0]
    assert rgb_high.rate_hz < rgb_low.rate_hz  # high load: one rung down


def test_shared_rate_ties_the_followers_to_the_first_sensor_and_each_chooses_its_setting() -> None:
    """``shared_rate``: the detector runs on every new frame of its fastest input, so its inputs move as one."""
    config = ActionSpaceConfig(shared_rate=("rgb", "thermal", "radar"))
    sensors = [*_sensors(), DriverConfigBase(driver="sim", name="depth", modality="depth", resolution=(640, 480))]
    slots = build_slots(config, sensors, {"flir": FLIR_CAPS}, shared_rate=config.shared_rate)
    space = ActionSpace(slots, "factored")
    assert [s.follows for s in slots] == [None, 0, 0, None]
    assert slots[1].rates == (1.0, 5.0, 9.0, 9.0, 9.0)  # the leader's levels, clamped to the FLIR One
    assert space.blocks == (15, 2, 2, 5) and space.columns == 24  # followers: a setting each, no rate
    assert space.n == 15 * 2 * 2 * 5
    assert space.descriptions()[15:19] == ["flir 160x120", "flir 320x240", "radar velocity", "radar range"]
    for action in range(space.n):
        position = space.apply(space.maximum(), action)
        assert space.config_id(position) == action
        cam, flir, radar, _ = space.requests(position)
        assert radar.rate_hz == cam.rate_hz and flir.rate_hz == min(cam.rate_hz, 9.0)
    top = space.requests(space.maximum())
    assert [c.rate_hz for c in top] == [30.0, 9.0, 30.0, 30.0]
    # what the drivers report is tied back to the leader's rate: the cells stay a position the table can name
    applied = {"cam": dataclasses.replace(top[0], rate_hz=5.0), "flir": top[1], "radar": top[2]}
    assert space.nearest(applied)[:3] == ((2, 1), (1, 1), (1, 1))
    assert space.describe(space.config_id(space.nearest(applied))).startswith(
        "cam 1280x720@5Hz flir 320x240@5Hz radar range@5Hz")


def test_shared_rate_moves_only_the_leaders_rate() -> None:
    config = ActionSpaceConfig(shared_rate=("rgb", "radar"))
    space = ActionSpace(build_slots(config, _sensors(), shared_rate=config.shared_rate), "moves")
    names = [space.describe(a) for a in range(space.n)]
    assert "radar rate up" not in names and "flir rate up" in names
    start = space.maximum()
    down = space.apply(start, names.index("cam rate down"))
    assert down[0][1] == down[2][1] == start[0][1] - 1 and down[1] == start[1]


def test_shared_rate_names_controlled_modalities_only() -> None:
    with pytest.raises(ValueError, match="shared_rate: depth not among the controlled modalities"):
        ActionSpaceConfig(modalities=("rgb", "thermal"), shared_rate=("rgb", "depth"))


def test_shared_rate_shapes_the_learner_not_the_baselines() -> None:
    from respecd.config import load_profile
    from respecd.control.controller import Controller

    profile = load_profile("builtin:sim-rover")
    actions = profile.controller.actions.model_copy(update={"shared_rate": ("rgb", "thermal", "radar")})
    tied = profile.controller.model_copy(update={"actions": actions})
    learner = Controller.from_profile(tied.model_copy(update={"policy": "learn"}), profile)
    heuristic = Controller.from_profile(tied.model_copy(update={"policy": "heuristic"}), profile)
    assert [s.follows for s in learner.space.slots if s.modality in ("thermal", "radar")] == [0, 0]
    assert all(s.follows is None for s in heuristic.space.slots)
    assert learner.layout()["actions"]["space"]["slots"][1]["follows"] == learner.space.slots[0].name
