"""The outcome cache: keys follow the checkpoint and the configuration, outcomes replay exactly."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from respecd.config import load_profile
from respecd.lab.experiment.cache import OutcomeCache, fingerprint, model_hash, outcome_key
from respecd.lab.experiment.frames import frame_id, frame_time, previous, render
from respecd.lab.experiment.outcomes import Evaluator
from respecd.lab.experiment.rollout import Piece, Rollout
from respecd.lab.experiment.setup import load_detector, perception_identity
from respecd.messages import SensorConfig
from respecd.sim.config import SimulationConfig
from respecd.sim.world import World

TINY_MODEL = {"rgb_widths": [4, 8, 8, 16, 16], "aux_widths": [4, 8, 8, 16, 16], "neck_widths": [8, 16, 16],
              "reg_max": 4}


def tiny_profile(tmp_path: Path) -> object:
    """sim-rover with a very narrow detector and one RGB resolution, so a test infers in milliseconds."""
    from importlib import resources

    doc = yaml.safe_load((resources.files("respecd.profiles") / "sim-rover.yaml").read_text())
    doc["perception"] = {"model": TINY_MODEL, "torch_threads": 1}
    doc["controller"] = {"actions": {"rgb_resolutions": [[640, 360]], "rate_levels_hz": [1, 10, 30]}}
    path = tmp_path / "tiny.yaml"
    path.write_text(yaml.safe_dump(doc))
    return load_profile(path)


@pytest.fixture(scope="module")
def profile(tmp_path_factory: pytest.TempPathFactory) -> object:
    return tiny_profile(tmp_path_factory.mktemp("profile"))


def test_fingerprint_changes_with_checkpoint_and_settings(profile) -> None:
    a = load_detector(profile, random_init=True, seed=1)
    b = load_detector(profile, random_init=True, seed=2)
    assert model_hash(a.model) == model_hash(load_detector(profile, random_init=True, seed=1).model)
    assert model_hash(a.model) != model_hash(b.model)
    ident = perception_identity(a, profile)
    assert fingerprint(model_hash(a.model), ident) != fingerprint(model_hash(b.model), ident)
    stricter = dict(ident, settings={**ident["settings"], "score_threshold": 0.5})
    assert fingerprint(model_hash(a.model), ident) != fingerprint(model_hash(a.model), stricter)


def test_fingerprint_changes_with_the_confidence_calibration(profile) -> None:
    """The calibration rides in the checkpoint beside the weights, not in the state dict."""
    from respecd.perception.calibration import ScoreCalibration

    detector = load_detector(profile, random_init=True, seed=1)
    weights = model_hash(detector.model)
    raw = fingerprint(weights, perception_identity(detector, profile))
    detector.model.score_calibration = ScoreCalibration({"640x360": (1.5, 1.9)})
    calibrated = fingerprint(weights, perception_identity(detector, profile))
    detector.model.score_calibration = ScoreCalibration({"640x360": (1.5, 2.0)})
    assert len({raw, calibrated, fingerprint(weights, perception_identity(detector, profile))}) == 3


def test_fingerprint_covers_the_code_of_every_stored_field() -> None:
    """An outcome stores the feature extractor's luminance and motion: the modules that
    compute them must be in the fingerprint, or a change to them would replay stale values."""
    import inspect
    from pathlib import PurePath

    from respecd.control import features, imagestats
    from respecd.lab.experiment import outcomes
    from respecd.lab.experiment.cache import SOURCE_MODULES
    from respecd.perception import calibration

    fingerprinted = {(package, name) for package, names in SOURCE_MODULES.items() for name in names}
    for module in (features, imagestats, outcomes, calibration):
        package, name = module.__name__.rsplit(".", 1)[0], PurePath(inspect.getfile(module)).name
        assert (package, name) in fingerprinted, module.__name__


def test_key_changes_with_configuration_and_attribution() -> None:
    rgb = SensorConfig("rgb", rate_hz=10.0, resolution=(640, 360))
    radar = SensorConfig("radar", rate_hz=10.0, mode="range")

    def key(*configs: SensorConfig, t: float = 2.35, attribute: bool = False, slot: int | None = None) -> str:
        return outcome_key("fp", "w", [frame_id(c, t, slot).key() for c in configs], attribute)

    base = key(rgb, radar)
    assert base == key(radar, rgb)  # order of sensors does not matter
    assert base == key(rgb, radar, t=2.39)  # same newest frames at 10 Hz
    assert base != key(rgb, radar, t=2.41)  # a new frame arrived
    assert base != key(SensorConfig("rgb", rate_hz=10.0, resolution=(960, 540)), radar)
    assert base != key(SensorConfig("rgb", rate_hz=5.0, resolution=(640, 360)), radar)
    assert base != key(rgb, SensorConfig("radar", rate_hz=10.0, mode="velocity"))
    assert base != key(rgb, radar, attribute=True)
    assert key(rgb, radar, slot=1) == key(rgb, radar, t=7.0, slot=5)  # static scene: noise slot 1 of 4
    assert outcome_key("fp1", "w", ["x"], False) != outcome_key("fp2", "w", ["x"], False)


def test_frame_time_and_stale_frames() -> None:
    assert frame_time(2.35, 10.0) == pytest.approx(2.3)
    assert frame_time(2.35, 1.0) == 2.0
    assert frame_time(3.0, 30.0) == pytest.approx(3.0)
    fid = frame_id(SensorConfig("rgb", rate_hz=5.0, resolution=(640, 360)), 1.0)
    assert previous(fid, 5.0).t_us == 800_000


def test_render_is_deterministic_per_frame() -> None:
    world = World(SimulationConfig(scenarios=["good-light-moving"]), 3)
    fid = frame_id(SensorConfig("rgb", rate_hz=10.0, resolution=(640, 360)), 1.23)
    a, b = render(world, fid), render(world, fid)
    assert np.array_equal(a.data, b.data)
    later = render(world, frame_id(SensorConfig("rgb", rate_hz=10.0, resolution=(640, 360)), 1.53))
    assert not np.array_equal(a.data, later.data)


def test_outcome_is_computed_once_and_replayed(profile, tmp_path: Path) -> None:
    detector = load_detector(profile, random_init=True)
    fp = fingerprint(model_hash(detector.model), perception_identity(detector, profile))
    cache = OutcomeCache(tmp_path / "o.sqlite")
    evaluator = Evaluator(detector, cache, fp)
    world = Rollout(profile, evaluator, {}).world(Piece("poor-light-moving", 1, 5.0))
    configs = {"rgb": SensorConfig("rgb", rate_hz=10.0, resolution=(640, 360)),
               "thermal": SensorConfig("thermal", rate_hz=10.0, resolution=(160, 120)),
               "radar": SensorConfig("radar", rate_hz=10.0, mode="range")}
    first = evaluator.outcome(world, configs, 2.05, attribute=True)
    assert (cache.misses, cache.hits) == (1, 0)
    assert first.luminance is not None and first.motion is not None and first.radar_points is not None
    again = evaluator.outcome(world, configs, 2.09, attribute=True)  # same frames at 10 Hz
    assert (cache.misses, cache.hits) == (1, 1)
    assert np.array_equal(again.boxes, first.boxes) and again.conf_agg == first.conf_agg
    cache.close()
    reopened = OutcomeCache(tmp_path / "o.sqlite")  # and from disk, in a later run
    ids = evaluator.frame_ids(configs, 2.05)
    assert reopened.get(evaluator.key(world, ids, evaluator.previous_ids(ids, configs), True)) == first.to_json()
    reopened.close()


def test_an_outcome_without_an_rgb_frame_is_drawn_at_the_rgb_cameras_size(profile) -> None:
    """With the RGB camera off its boxes still live in its pixels (the ground truth is drawn there): the
    detector's grid is the camera's size, and two sizes are two outcomes, whichever is asked for first."""
    detector = load_detector(profile, random_init=True)
    cache = OutcomeCache(None)
    fp = fingerprint(model_hash(detector.model), perception_identity(detector, profile))
    evaluator = Evaluator(detector, cache, fp)
    world = Rollout(profile, evaluator, {}).world(Piece("behind-curtain", 1, 5.0))
    align, grids = detector.aligner.align, []

    def recording_align(frames, rgb_size=None):  # type: ignore[no-untyped-def]
        aligned = align(frames, rgb_size)
        grids.append(aligned.size)
        return aligned

    detector.aligner.align = recording_align
    for size in ((1280, 720), (640, 360), (1280, 720)):
        configs = {"rgb": SensorConfig("rgb", False, 10.0, size),
                   "thermal": SensorConfig("thermal", rate_hz=10.0, resolution=(160, 120)),
                   "radar": SensorConfig("radar", rate_hz=10.0, mode="range")}
        evaluator.outcome(world, configs, 2.05, attribute=False)
    assert grids == [(1280, 720), (640, 360)] and (cache.misses, cache.hits) == (2, 1)


def test_a_computed_outcome_is_the_one_a_later_run_replays(tmp_path: Path) -> None:
    """The cache keeps boxes to 0.01 px and scores to 1e-5; a run that computes an outcome must use those values
    too, or a run with misses and one from the cache score a box at the IoU or ranking edge differently."""
    profile = load_profile("builtin:sim-rover")
    detector = load_detector(profile)  # the shipped net: real detections to round
    fp = fingerprint(model_hash(detector.model), perception_identity(detector, profile))
    cache = OutcomeCache(tmp_path / "o.sqlite")
    evaluator = Evaluator(detector, cache, fp)
    world = Rollout(profile, evaluator, {}).world(Piece("good-light-static", 3, 5.0))
    configs = {"rgb": SensorConfig("rgb", rate_hz=1.0, resolution=(640, 360)),
               "thermal": SensorConfig("thermal", rate_hz=1.0, resolution=(160, 120))}
    computed = evaluator.outcome(world, configs, 1.0, attribute=False)
    assert cache.misses == 1 and len(computed.scores) > 0
    cache.close()
    reopened = OutcomeCache(tmp_path / "o.sqlite")
    replayed = Evaluator(detector, reopened, fp).outcome(world, configs, 1.0, False)
    reopened.close()
    assert np.array_equal(replayed.boxes, computed.boxes) and np.array_equal(replayed.scores, computed.scores)
    assert replayed.conf_agg == computed.conf_agg


def test_motion_does_not_depend_on_which_rate_asked_for_a_frame_first(profile) -> None:
    """At t = 3.0 s a thermal camera at 5 Hz and one at 10 Hz deliver the same frame, but the
    motion cue compares it with the frame 0.2 s or 0.1 s before: two outcomes, whatever the
    order in which they are asked for. A night scene: by day (thermal crossover) the walker may
    barely differ from the sun-warmed room in thermal."""
    detector = load_detector(profile, random_init=True)
    fp = fingerprint(model_hash(detector.model), perception_identity(detector, profile))

    def configs(thermal_hz: float) -> dict[str, SensorConfig]:
        return {"rgb": SensorConfig("rgb", rate_hz=1.0, resolution=(640, 360)),
                "thermal": SensorConfig("thermal", rate_hz=thermal_hz, resolution=(160, 120))}

    motion = {}
    for order in ((5.0, 10.0), (10.0, 5.0)):
        evaluator = Evaluator(detector, OutcomeCache(None), fp)
        world = Rollout(profile, evaluator, {}).world(Piece("poor-light-moving", 2, 5.0))
        for hz in order:
            motion[order, hz] = evaluator.outcome(world, configs(hz), 3.0, attribute=False).motion
        assert evaluator.cache.misses == 2
    assert motion[(5.0, 10.0), 5.0] == motion[(10.0, 5.0), 5.0]
    assert motion[(5.0, 10.0), 10.0] == motion[(10.0, 5.0), 10.0]
    assert motion[(5.0, 10.0), 5.0] != motion[(5.0, 10.0), 10.0]  # a person walked further in 0.2 s
