"""State factors: bin edges, ConfAgg, index <-> names, window features from real images."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from respecd.control.config import ALL_FACTORS, Thresholds
from respecd.control.features import FeatureExtractor, Sample, Window, scene_light
from respecd.control.state import Observation, StateSpace, bin3, dominant
from respecd.messages import Bundle, Frame, Health, Percept, SyncStats, conf_agg

REAL = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real"


def _percept(t: float, frames: dict, health: Health = Health.GOOD, conf: float = 0.5) -> Percept:
    bundle = Bundle(t, frames, SyncStats(10.0, 1.0, 0.0, health))
    return Percept(t, (), conf, None, 0.02, bundle)


@pytest.mark.parametrize(
    ("value", "expected"),
    [(0.0, 0), (0.2999, 0), (0.3, 1), (0.5999, 1), (0.6, 2), (1.0, 2), (-1.0, 0)],
)
def test_bin3_edges_low_inclusive_high_inclusive(value: float, expected: int) -> None:
    assert bin3(value, (0.3, 0.6)) == expected


def test_bin3_equal_edges_has_no_middle_bin() -> None:
    assert [bin3(v, (0.5, 0.5)) for v in (0.49, 0.5, 0.51)] == [0, 2, 2]


@pytest.mark.parametrize(
    ("confidences", "expected"),
    [([], 0.0), ([0.7], 0.7), ([0.4, 0.8], 0.6), ([0.1, 0.9, 0.5, 0.8, 0.2], (0.9 + 0.8 + 0.5) / 3)],
)
def test_conf_agg_top_three_mean(confidences: list[float], expected: float) -> None:
    assert conf_agg(confidences) == pytest.approx(expected)


def test_state_index_round_trips_every_state() -> None:
    space = StateSpace(ALL_FACTORS, Thresholds(), ("rgb", "thermal", "radar"))
    assert space.dims == (3, 3, 3, 3, 3, 3, 4)
    assert space.size == 729 * 4
    for index in (0, 1, 728, 1000, space.size - 1):
        bins = space.unindex(index)
        assert space.index(bins) == index
        assert space.from_names(space.names(bins)) == bins
        assert space.parse(space.describe(bins)) == bins
    assert space.names(space.unindex(0))["illumination"] == "dark"
    assert space.names(space.unindex(space.size - 1)) == {
        "illumination": "bright", "motion": "fast", "radar_density": "dense", "load": "high",
        "sync": "poor", "confidence": "high", "dominant": "radar",
    }
    with pytest.raises(ValueError):
        space.unindex(space.size)
    with pytest.raises(ValueError):
        space.index((3, 0, 0, 0, 0, 0, 0))
    with pytest.raises(ValueError, match="expected 7 values joined by '/'"):
        space.parse("bright/still")
    with pytest.raises(ValueError, match="a value is not a bin of its factor"):
        space.parse("bright/still/dense/medium/good/high/sonar")


def test_bins_from_observation_uses_profile_thresholds() -> None:
    space = StateSpace(ALL_FACTORS, Thresholds(), ("rgb", "thermal"))
    obs = Observation(
        t=1.0, n_percepts=5, illumination=0.1, motion_image=0.01, motion_imu=0.6, radar_points=25.0,
        load=0.6, sync=1.6, conf_agg=0.31, contributions={"rgb": 0.1, "thermal": 0.8, "radar": 0.1},
    )
    assert space.names(space.bins(obs)) == {
        "illumination": "dark", "motion": "fast", "radar_density": "dense", "load": "medium",
        "sync": "poor", "confidence": "medium", "dominant": "thermal",
    }
    unknown = Observation(t=0.0)
    assert space.names(space.bins(unknown))["illumination"] == "dim"  # unknown light is not "dark"
    assert space.names(space.bins(unknown))["dominant"] == "none"


def test_dominant_ignores_modalities_outside_the_state() -> None:
    assert dominant({"depth": 0.9, "rgb": 0.1}, ("rgb", "thermal")) == "rgb"
    assert dominant(None, ("rgb",)) == "none"
    assert dominant({"rgb": 0.0}, ("rgb",)) == "none"


def test_real_night_image_is_dark_and_day_image_is_not() -> None:
    night = REAL / "llvip_pairs" / "visible" / "010005.jpg"
    day = REAL / "tardal_ir_vis_samples" / "vi" / "ROAD_040.jpg"
    if not night.exists() or not day.exists():
        pytest.skip(f"shared real captures not found under {REAL}")
    th = Thresholds()
    samples = [FeatureExtractor().sample(_percept(0.0, {"rgb": Frame("rgb", 0.0, 0, cv2.imread(str(p)))}))
               for p in (night, day)]
    assert bin3(samples[0].luminance, th.illumination) == 0
    assert bin3(samples[1].luminance, th.illumination) >= 1


def _rgb(seq: int, image: np.ndarray) -> Frame:
    return Frame("rgb", seq / 10, seq, image)


def test_motion_score_is_noise_relative_on_real_frames() -> None:
    first, second = (REAL / "llvip_pairs" / "visible" / f"{i}.jpg" for i in ("190001", "190002"))
    if not first.exists():
        pytest.skip(f"shared real captures not found under {REAL}")
    a, b = cv2.imread(str(first)), cv2.imread(str(second))
    noisy = np.clip(a + np.random.default_rng(0).normal(0, 6, a.shape), 0, 255).astype(np.uint8)
    still, moved = FeatureExtractor(), FeatureExtractor()
    still.sample(_percept(0.0, {"rgb": _rgb(0, a)}))
    moved.sample(_percept(0.0, {"rgb": _rgb(0, a)}))
    # sensor noise alone: p99/median of |Gaussian| differences is 2.576/0.674 = 3.8
    assert still.sample(_percept(0.1, {"rgb": _rgb(1, noisy)})).motion_image == pytest.approx(3.8, abs=0.4)
    assert moved.sample(_percept(0.1, {"rgb": _rgb(1, b)})).motion_image > Thresholds().motion_image[1]


def test_motion_score_skips_repeats_and_resolution_changes_and_uses_thermal() -> None:
    rng = np.random.default_rng(1)
    extractor = FeatureExtractor()
    big = rng.integers(0, 255, (720, 1280, 3), dtype=np.uint8)
    small = rng.integers(0, 255, (360, 640, 3), dtype=np.uint8)
    assert extractor.sample(_percept(0.0, {"rgb": _rgb(0, big)})).motion_image is None  # first frame
    assert extractor.sample(_percept(0.1, {"rgb": _rgb(0, big)})).motion_image is None  # same frame again
    assert extractor.sample(_percept(0.2, {"rgb": _rgb(1, small)})).motion_image is None  # new resolution
    warm = np.full((120, 160), 29500, np.uint16) + rng.integers(0, 20, (120, 160), dtype=np.uint16)
    walked = warm.copy()
    walked[40:100, 100:120] = 31000  # a person at 310 K (centikelvin counts) stepped into view
    frames = [Frame("thermal", 0.0, 0, warm), Frame("thermal", 0.1, 1, walked)]
    extractor.sample(_percept(0.3, {"thermal": frames[0]}))
    score = extractor.sample(_percept(0.4, {"thermal": frames[1]})).motion_image
    assert score > Thresholds().motion_image[1]


@pytest.mark.parametrize("resolution", [(160, 120), (320, 240)])
def test_static_thermal_scene_reads_still(resolution: tuple[int, int]) -> None:
    """The simulated thermal camera's noise is under one count per block mean: rounding
    block means to whole counts made a static scene score exactly 4.0 or 5.0, and 5.0 is
    the still/slow edge."""
    from respecd.sim.config import SimulationConfig
    from respecd.sim.render import render_thermal
    from respecd.sim.world import World

    state = World(SimulationConfig(scenarios=["poor-light-static"]), 501).state_at(5.0)
    still_below = Thresholds().motion_image[0]
    for pair in range(4):
        first, second = (render_thermal(state, resolution, np.random.default_rng([pair, k])) for k in (0, 1))
        extractor = FeatureExtractor()
        extractor.sample(_percept(0.0, {"thermal": Frame("thermal", 0.0, 0, first)}))
        score = extractor.sample(_percept(0.1, {"thermal": Frame("thermal", 0.1, 1, second)})).motion_image
        assert score == pytest.approx(3.8, abs=0.6)
        assert score < still_below


def test_imu_radar_and_sync_features() -> None:
    imu = Frame("imu", 0.0, 0, np.array([0, 0, 9.81, 0.3, 0.4, 0.0], np.float32))
    radar = Frame("radar", 0.0, 0, np.zeros((7, 5), np.float32))
    sample = FeatureExtractor().sample(_percept(0.0, {"imu": imu, "radar": radar}, Health.FAIR))
    assert sample.gyro == pytest.approx(0.5)
    assert sample.radar_points == 7.0
    assert sample.sync_level == 1
    assert sample.luminance is None


def test_window_averages_prunes_and_keeps_last_scene_values() -> None:
    window = Window(window_s=1.0, latency_budget_s=0.2)
    window.add(Sample(t=0.2, conf_agg=0.2, latency_s=0.05, luminance=0.1, radar_points=10, sync_level=0))
    window.add(Sample(t=0.9, conf_agg=0.6, latency_s=0.15, luminance=0.3, sync_level=2,
                      contributions={"rgb": 0.2, "thermal": 0.8}))
    obs = window.observe(1.0, cpu=0.3)
    assert obs.n_percepts == 2
    assert obs.conf_agg == pytest.approx(0.4)
    assert obs.illumination == pytest.approx(0.2)
    assert obs.radar_points == 10
    assert obs.sync == pytest.approx(1.0)
    assert obs.load == pytest.approx(0.5)  # latency 0.1 s of a 0.2 s budget beats CPU 0.3
    assert obs.busy == pytest.approx(0.2)  # 0.05 + 0.15 s of inference in a 1 s window
    later = window.observe(2.5, cpu=0.9)  # both samples aged out
    assert later.n_percepts == 0 and later.conf_agg == 0.0 and later.busy == 0.0
    assert later.illumination == pytest.approx(0.2)  # last known light, not "unknown"
    assert later.contributions == {"rgb": 0.2, "thermal": 0.8}
    assert later.load == pytest.approx(0.9)


def test_window_averages_the_truth_quality_only_of_samples_that_carry_it() -> None:
    window = Window(window_s=1.0, latency_budget_s=0.2)
    window.add(Sample(t=0.2, conf_agg=0.9, latency_s=0.05, truth_quality=0.5))
    window.add(Sample(t=0.9, conf_agg=0.9, latency_s=0.05))
    assert window.observe(1.0).truth_quality == pytest.approx(0.5)
    assert window.observe(2.5).truth_quality is None  # the daemon's windows: no truth


def test_auto_exposure_is_undone_for_illumination() -> None:
    # 5 Hz in a dark room: 200 ms at gain 3 gives a frame as bright as daylight at 1/30 s
    assert scene_light(0.42, {"exposure_s": 0.2, "gain": 3.0}) == pytest.approx(0.42 / 18)
    assert scene_light(0.42, {}) == 0.42  # a camera that does not say keeps the raw mean
    assert scene_light(0.9, {"exposure_s": 0.01, "gain": 1.0}) == 1.0
