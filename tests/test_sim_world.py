"""The simulated world: determinism, the scenario sequence and the physics the controller relies on."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from respecd.config import load_profile
from respecd.errors import ConfigError
from respecd.sim.camera import ground_truth
from respecd.sim.radar_model import radar_figures
from respecd.sim.render import render_depth, render_imu, render_radar, render_rgb, render_thermal
from respecd.sim.state import Occluder, SceneState, Target
from respecd.sim.world import SCENARIOS, SimulationConfig, World, make_world

REPO = Path(__file__).resolve().parents[1]


def _rng(seed: int = 0) -> np.random.Generator:
    return np.random.default_rng(seed)


def _state(t: float = 3.0, seed: int = 7) -> SceneState:
    return World(SimulationConfig(), seed).state_at(t)


def _person(x: float = 0.0, z: float = 5.0, vx: float = 0.0, temperature_k: float = 304.0) -> Target:
    height = 1.7
    return Target(0, (x, 0.45 - height / 2, z), (vx, 0.0, 0.0), (0.5, height), temperature_k, (40, 60, 200), abs(vx))


def _wall(z: float = 3.0, kind: str = "solid") -> Occluder:
    smoke = kind == "smoke"
    return Occluder(
        kind,
        (0.0, -0.5, z),
        (3.0, 2.5),
        0.95 if smoke else 1.0,
        0.25 if smoke else 0.0,
        2.0 if smoke else float("inf"),
        296.0,
        (150, 150, 150),
    )  # type: ignore[arg-type]


def _scene(*targets: Target, occluders: tuple[Occluder, ...] = (), light: float = 0.9) -> SceneState:
    """A room of a night scene (20-25 C air: people well above it), lit as asked."""
    return replace(_state(33.0, 3), targets=targets, occluders=occluders, light=light, ego_speed=0.0, ego_accel=0.0)


def test_scenarios_in_paper_order_then_the_radar_only_one() -> None:
    assert SCENARIOS == (
        "good-light-static",
        "poor-light-static",
        "good-light-moving",
        "poor-light-moving",
        "occlusion-partial",
        "occlusion-smoke",
        "behind-curtain",
    )
    assert SimulationConfig().scenarios == list(SCENARIOS)
    assert load_profile("builtin:sim-rover").simulation.scenarios == list(SCENARIOS)


def test_sequence_and_loop() -> None:
    world = World(SimulationConfig(scenario_duration_s=10), seed=1)
    n = len(SCENARIOS)
    assert [world.state_at(10 * i + 1).scenario for i in range(n + 1)] == [*SCENARIOS, SCENARIOS[0]]
    first, again = world.state_at(1.0), world.state_at(10.0 * n + 1.0)
    assert first.scenario == again.scenario and first.segment != again.segment
    assert first.targets != again.targets  # each pass draws fresh parameters
    held = World(SimulationConfig(scenario_duration_s=10, loop=False), seed=1)
    assert held.state_at(500.0).scenario == SCENARIOS[-1]


def test_world_is_a_pure_function_of_config_seed_and_time() -> None:
    config = SimulationConfig()
    a, b = World(config, 3), World(config, 3)
    times = [150.0, 0.0, 47.25, 95.5, 47.25]  # out of order on purpose
    assert [a.state_at(t) for t in times] == [b.state_at(t) for t in reversed(times)][::-1]
    assert World(config, 4).state_at(47.25) != a.state_at(47.25)
    assert World(SimulationConfig(seed=3), 99).state_at(10.0) == a.state_at(10.0)  # the profile's seed wins


def test_make_world_is_shared() -> None:
    config = SimulationConfig(scenario_duration_s=12)
    assert make_world(config, 5) is make_world(SimulationConfig(scenario_duration_s=12), 5)
    assert make_world(config, 6) is not make_world(config, 5)


def test_parameters_stay_in_their_ranges() -> None:
    config = SimulationConfig()
    for seed in range(20):
        world = World(config, seed)
        for i, name in enumerate(SCENARIOS):
            state = world.state_at(30.0 * i + 15.0)
            assert 1 <= len(state.targets) <= 3
            light = config.poor_light if "poor" in name else config.good_light
            assert light[0] <= state.light <= light[1]
            if "static" in name or "occlusion" in name:
                assert all(t.speed_mps == 0 for t in state.targets)
            far = 8.0 if name == "behind-curtain" else 12.0  # an indoor curtain: people nearer
            for target in state.targets:
                assert 1.5 <= target.position[2] <= far + 0.5  # 2-12 m, give or take the rover's motion


def test_renderers_are_deterministic() -> None:
    state = _state(100.0)
    for render in (
        lambda r: render_rgb(state, (640, 360), 1 / 30, r),
        lambda r: render_thermal(state, (160, 120), r),
        lambda r: render_depth(state, (424, 240), r),
        lambda r: render_radar(state, "range", 10, r),
        lambda r: render_imu(state, r),
    ):
        assert np.array_equal(render(_rng(5)), render(_rng(5)))


def test_layouts() -> None:
    state = _state(40.0)
    rgb = render_rgb(state, (960, 540), 1 / 30, _rng())
    assert rgb.shape == (540, 960, 3) and rgb.dtype == np.uint8
    thermal = render_thermal(state, (320, 240), _rng())
    assert thermal.shape == (240, 320) and thermal.dtype == np.uint16
    assert 280 * 100 < np.median(thermal) < 310 * 100  # centikelvin at room temperature
    depth = render_depth(state, (848, 480), _rng())
    assert depth.shape == (480, 848) and depth.dtype == np.uint16
    valid = depth[depth > 0]
    assert valid.size and valid.min() >= 300 and valid.max() <= 3000
    radar = render_radar(state, "range", 10, _rng())
    assert radar.ndim == 2 and radar.shape[1] == 5 and radar.dtype == np.float32
    assert (radar[:, 1] > 0).all()  # y is the boresight
    imu = render_imu(state, _rng())
    assert imu.shape == (6,) and imu.dtype == np.float32 and abs(imu[1] + 9.81) < 0.5


def _rgb(scene: SceneState, exposure_s: float = 1 / 30, seed: int = 1) -> np.ndarray:
    return render_rgb(scene, (640, 360), exposure_s, _rng(seed))


def _thermal(scene: SceneState) -> np.ndarray:
    return render_thermal(scene, (160, 120), _rng(1))


def _person_signal(render, scene: SceneState) -> np.ndarray:
    """What the person adds to the image: the same render (same noise) with and without them."""
    return render(scene).astype(np.float64) - render(replace(scene, targets=())).astype(np.float64)


def test_darkness_kills_rgb_contrast_but_not_thermal() -> None:
    scene = _scene(_person(z=4.0))
    x1, y1, x2, y2 = (int(v) for v in ground_truth(scene, (640, 360))[0]["box"])
    bright = np.abs(_person_signal(_rgb, scene)[y1:y2, x1:x2]).mean()
    dark_scene = replace(scene, light=0.01)
    dark = np.abs(_person_signal(_rgb, dark_scene)[y1:y2, x1:x2]).mean()
    noise = (_rgb(dark_scene).astype(float) - _rgb(dark_scene, seed=2)).std() / np.sqrt(2)
    assert dark < 0.1 * bright and dark < noise  # the person is below the noise floor
    assert _rgb(dark_scene).mean() < 0.25 * _rgb(scene).mean()
    assert np.array_equal(_thermal(scene), _thermal(dark_scene))
    tx1, ty1, tx2, ty2 = (int(v) for v in ground_truth(scene, (160, 120))[0]["box"])
    assert _person_signal(_thermal, scene)[ty1:ty2, tx1:tx2].max() > 500  # > 5 K warmer than the wall


def test_solid_occluder_blocks_rgb_thermal_and_radar() -> None:
    scene = _scene(_person(z=6.0), occluders=(_wall(3.0),))
    assert ground_truth(scene, (640, 360))[0]["visible"] == 0.0
    rgb = _person_signal(_rgb, scene)
    thermal = _person_signal(_thermal, scene)
    assert np.abs(rgb).max() == 0 and np.abs(thermal).max() == 0
    assert _radar_hits(scene, "range") == 0
    assert _radar_hits(replace(scene, occluders=()), "range") > 10


def test_smoke_blocks_rgb_mostly_thermal_but_not_radar() -> None:
    clear = _scene(_person(z=6.0))
    smoky = replace(clear, occluders=(_wall(3.0, "smoke"),))
    assert ground_truth(smoky, (640, 360))[0]["smoke"] == pytest.approx(0.95)

    def rgb(scene: SceneState) -> float:
        return float(np.abs(_person_signal(_rgb, scene)).sum())

    def thermal(scene: SceneState) -> float:
        return float(np.abs(_person_signal(_thermal, scene)).sum())

    assert rgb(smoky) < 0.12 * rgb(clear)
    assert 0.1 * thermal(clear) < thermal(smoky) < 0.4 * thermal(clear)  # 25 % transmission
    assert _radar_hits(smoky, "range") > 0.5 * _radar_hits(clear, "range")


def test_curtain_and_dense_fog_blind_both_cameras_but_not_radar() -> None:
    """Cloth and water fog stop visible light and LWIR; thin fabric costs 60 GHz a few dB."""
    clear = _scene(_person(z=5.0))
    curtain = replace(_wall(3.0, "smoke"), kind="curtain", rgb_opacity=1.0, thermal_transmission=0.005,
                      radar_loss_db=3.0)
    fog = replace(_wall(3.0, "smoke"), rgb_opacity=0.995, thermal_transmission=0.005, radar_loss_db=0.3)
    clear_rgb = float(np.abs(_person_signal(_rgb, clear)).sum())
    clear_thermal = float(np.abs(_person_signal(_thermal, clear)).sum())
    for occluder in (curtain, fog):
        scene = replace(clear, occluders=(occluder,))
        truth = ground_truth(scene, (640, 360))[0]
        assert truth["visible"] == 1.0  # not hidden: the radar still sees all of the person
        assert truth["transmission"]["rgb"] < 0.01 and truth["transmission"]["thermal"] < 0.01
        assert float(np.abs(_person_signal(_rgb, scene)).sum()) < 0.02 * clear_rgb
        assert float(np.abs(_person_signal(_thermal, scene)).sum()) < 0.05 * clear_thermal
        assert _radar_hits(scene, "range") > 0.6 * _radar_hits(clear, "range")
    assert ground_truth(clear, (640, 360))[0]["transmission"] == {"rgb": 1.0, "thermal": 1.0}


def test_behind_curtain_scenario_puts_everyone_behind_it() -> None:
    index = SCENARIOS.index("behind-curtain")
    kinds = set()
    for seed in range(8):
        state = World(SimulationConfig(), seed).state_at(index * 30 + 5.0)
        assert state.scenario == "behind-curtain" and state.light >= SimulationConfig().good_light[0]
        (occluder,) = state.occluders
        kinds.add(occluder.kind)
        for truth in ground_truth(state, (1280, 720)):
            assert truth["transmission"]["rgb"] < 0.02 and truth["transmission"]["thermal"] < 0.02
    assert kinds == {"curtain", "smoke"}  # a fabric curtain or a dense fog bank


def _radar_hits(scene: SceneState, mode: str, rate_hz: float = 10) -> int:
    """Radar points within 0.8 m of the person, over 20 frames."""
    x, _, z = scene.targets[0].position
    hits = 0
    for seed in range(20):
        cloud = render_radar(scene, mode, rate_hz, _rng(seed))
        hits += int((np.hypot(cloud[:, 0] - x, cloud[:, 1] - z) < 0.8).sum())
    return hits


def test_radar_modes_trade_range_resolution_for_velocity_resolution() -> None:
    for rate in (1, 10, 20, 30):
        rng_fig, vel_fig = radar_figures("range", rate), radar_figures("velocity", rate)
        assert rng_fig.range_res_m < vel_fig.range_res_m / 3
        assert vel_fig.velocity_res_mps < rng_fig.velocity_res_mps
        assert rng_fig.cfar_range_m == vel_fig.cfar_range_m  # the modes trade resolution, not coverage
    assert radar_figures("velocity", 30).velocity_res_mps > radar_figures("velocity", 10).velocity_res_mps
    near, beyond = _scene(_person(z=11.5)), _scene(_person(z=16.0))
    for mode in ("range", "velocity"):
        assert _radar_hits(near, mode) > 0 and _radar_hits(beyond, mode) == 0  # the cfg stops at 14.99 m
    walker = _scene(_person(x=-2.0, z=3.0, vx=0.0))
    walker = replace(walker, targets=(replace(walker.targets[0], velocity=(0.0, 0.0, -1.6), speed_mps=1.6),))
    levels = {}
    for mode in ("range", "velocity"):
        speeds = np.concatenate([render_radar(walker, mode, 10, _rng(seed))[:, 3] for seed in range(5)])
        levels[mode] = len(np.unique(np.round(speeds, 4)))
    assert levels["velocity"] > 3 * levels["range"]  # Doppler bins of 0.035 m/s against 0.68 m/s


def test_fast_target_blurs_more_at_low_rate() -> None:
    scene = _scene(_person(x=-0.5, z=4.0, vx=1.5), light=0.02)

    def extent(exposure_s: float) -> int:
        signal = np.abs(_person_signal(lambda s: _rgb(s, exposure_s), scene)).mean(axis=(0, 2))
        return int((signal > 0.2 * signal.max()).sum())  # columns the person smears over

    assert extent(1 / 5) > extent(1 / 30) + 15  # 1.5 m/s at 4 m: ~17 px more per 1/30 s of exposure


def test_far_target_is_few_pixels() -> None:
    near, far = _scene(_person(z=2.0)), _scene(_person(z=12.0))
    box = ground_truth(far, (640, 360))[0]["box"]
    width, height = box[2] - box[0], box[3] - box[1]
    assert width < 20 and height < 70

    def painted(scene: SceneState) -> int:
        return int((np.abs(_person_signal(_rgb, scene)).sum(axis=2) > 0).sum())

    assert painted(far) < 0.01 * 640 * 360 and 20 * painted(far) < painted(near)  # under 1 % of the frame


def test_depth_sees_only_near_people() -> None:
    near, far = _scene(_person(z=2.5)), _scene(_person(z=5.0))
    for scene, expected in ((near, 2500), (far, 0)):
        x1, y1, x2, y2 = (int(v) for v in ground_truth(scene, (640, 480))[0]["box"])
        depth = render_depth(scene, (640, 480), _rng(1))[y1:y2, x1:x2]
        assert abs(float(np.median(depth)) - expected) < 60


def test_partial_occlusion_scenario_hides_part_of_a_person() -> None:
    visible = []
    for seed in range(6):
        state = World(SimulationConfig(), seed).state_at(4 * 30 + 5.0)
        assert state.scenario == "occlusion-partial" and state.occluders[0].kind == "solid"
        visible.append(ground_truth(state, (1280, 720))[0]["visible"])
    assert all(0.1 < v < 0.9 for v in visible), visible


def test_bad_simulation_section_names_the_line(tmp_path: Path) -> None:
    lines = (REPO / "configs" / "sim-rover.yaml").read_text().splitlines()
    line = next(i for i, s in enumerate(lines) if s.startswith("  scenarios:"))
    lines[line] = "  scenarios: [good-light-static, foggy-night]"
    path = tmp_path / "bad.yaml"
    path.write_text("\n".join(lines))
    with pytest.raises(ConfigError) as err:
        load_profile(path)
    assert any(
        p.startswith(f"{path}:{line + 1}: simulation.scenarios") and "foggy-night" in p for p in err.value.problems
    )
    with pytest.raises(ValueError, match="distance_m"):
        SimulationConfig(distance_m=(12.0, 2.0))


def test_a_nearer_person_hides_part_of_a_farther_one() -> None:
    back, front = _person(x=0.0, z=8.0), replace(_person(x=0.1, z=4.0), id=1)
    visible = {g["id"]: g["visible"] for g in ground_truth(_scene(back, front), (640, 360))}
    assert visible[1] == 1.0 and visible[0] < 0.3


def test_daylight_fades_thermal_contrast_and_night_keeps_it() -> None:
    """Good light is a sun-warmed room (thermal crossover): people read within a few kelvin of
    the air, while in the dark lab they stand 3-12 K above it. So by day RGB must carry."""
    day, night = [], []
    for seed in range(12):
        world = World(SimulationConfig(scenarios=["good-light-static", "poor-light-static"]), seed)
        for t, out in ((10.0, day), (40.0, night)):
            state = world.state_at(t)
            out += [target.temperature_k - state.room.ambient_k for target in state.targets]
    assert max(abs(d) for d in day) < 4.5 and np.median(np.abs(day)) < 2.0
    assert min(night) > 3.0
    assert any(d < 0 for d in day)  # sometimes the room is warmer than the clothing: the contrast inverts
