"""The detector's outcome for the frames a configuration delivers at one instant, cached.

``Evaluator.outcome`` renders the frames (``frames.py``), runs the real ``FusionDetector``
on them and extracts the scene features the controller's state needs, through the same
``FeatureExtractor`` the daemon uses (luminance, image difference to the sensor's previous
frame, radar point count). The result is stored in the ``OutcomeCache`` under the frames'
identity, so a second request for the same frames costs a dictionary lookup.

Attribution keeps a decaying scene score between calls inside the detector; the cache
stores the *fresh* score of this one call (None when nothing was detected), and the
rollout applies the decay, exactly as the daemon's detector would across its calls.
"""

from __future__ import annotations

import time
from collections import OrderedDict
from collections.abc import Collection, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from respecd.control.features import FeatureExtractor
from respecd.lab.experiment.cache import OutcomeCache, outcome_key
from respecd.lab.experiment.frames import FrameId, frame_id, imu_frame, previous, render, truth
from respecd.messages import Bundle, Frame, Health, Percept, SensorConfig, SyncStats
from respecd.sim.config import SimulationConfig
from respecd.sim.scenarios import SPECS
from respecd.sim.world import World

WORLD_SEGMENT_S = 3600.0  # one long segment: the same (scenario, seed) is the same world at any length
MOTION_IMAGERS = ("rgb", "thermal")  # the feature extractor scores motion on these

_GOOD_SYNC = SyncStats(30.0, 0.0, 0.0, Health.GOOD)


@dataclass(frozen=True)
class Outcome:
    """What one inference on one set of frames gave, plus the frames' scene features."""

    boxes: np.ndarray  # (P, 4) x1y1x2y2 in RGB pixels at the RGB frame's resolution
    scores: np.ndarray  # (P,)
    conf_agg: float
    contributions: dict[str, float] | None  # fresh scene score of this call (attributed calls only)
    luminance: float | None
    motion: float | None  # image motion score (RGB and thermal), as the feature extractor gives it
    radar_points: float | None

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> Outcome:
        return cls(np.asarray(d["boxes"], dtype=np.float32).reshape(-1, 4), np.asarray(d["scores"], dtype=np.float32),
                   float(d["conf_agg"]), d["contributions"], d["luminance"], d["motion"], d["radar_points"])

    def to_json(self) -> dict[str, Any]:
        return {"boxes": np.round(self.boxes, 2).tolist(), "scores": np.round(self.scores, 5).tolist(),
                "conf_agg": self.conf_agg, "contributions": self.contributions, "luminance": self.luminance,
                "motion": self.motion, "radar_points": self.radar_points}


def world_key(world: World) -> str:
    return f"{world.seed}:{world.config.model_dump_json()}"


class Evaluator:
    """Detector + cache: ``outcome(world, configs, t, attribute)`` for any configuration."""

    def __init__(self, detector: Any, cache: OutcomeCache, fingerprint: str) -> None:
        self.detector = detector
        self.cache = cache
        self.fingerprint = fingerprint
        self.inputs = ("rgb", *detector.model.spec.aux_modalities)  # modalities the network reads
        self.inference_s = 0.0  # wall time spent on cache misses (render + detector)
        self._frames: OrderedDict[tuple[str, str], Frame] = OrderedDict()  # a few recent renders
        self._worlds: dict[tuple[str, int], World] = {}

    def frame_ids(self, configs: Mapping[str, SensorConfig], t: float, slot: int | None = None) -> dict[str, FrameId]:
        """The newest frame of every enabled detector input at ``t`` (``slot``: static scene)."""
        return {m: frame_id(c, t, slot) for m, c in configs.items() if m in self.inputs and c.enabled}

    @staticmethod
    def previous_ids(ids: dict[str, FrameId], configs: Mapping[str, SensorConfig]) -> dict[str, FrameId]:
        """The frame before each imager's current one: what the motion cue compares it with."""
        return {m: previous(ids[m], configs[m].rate_hz) for m in MOTION_IMAGERS if m in ids}

    def key(self, world: World, ids: dict[str, FrameId], before: dict[str, FrameId], attribute: bool,
            rgb_size: tuple[int, int] | None = None) -> str:
        """The cache key of an outcome: every frame it was computed from (and without an RGB frame,
        the RGB camera's size its boxes are drawn at). The previous frames count because the imager's
        rate sets them and a thermal frame id does not hold the rate: without them the first rate to
        ask for a frame set its motion for every rate."""
        parts = [f.key() for f in ids.values()] + [f"before {f.key()}" for f in before.values()]
        return outcome_key(self.fingerprint, world_key(world), parts + canvas_parts(rgb_size), attribute)

    def outcome(self, world: World, configs: Mapping[str, SensorConfig], t: float, attribute: bool,
                slot: int | None = None) -> Outcome:
        """The detector's outcome at instant ``t`` for sensors in ``configs`` (by modality).

        ``slot``: in a static scene, the noise slot standing in for the frame time.
        """
        ids = self.frame_ids(configs, t, slot)
        before = self.previous_ids(ids, configs)
        rgb_size = rgb_canvas(configs, ids)
        key = self.key(world, ids, before, attribute, rgb_size)
        cached = self.cache.get(key)
        if cached is not None:
            return Outcome.from_json(cached)
        start = time.perf_counter()
        stored = self._compute(world, ids, before, attribute, rgb_size).to_json()
        self.inference_s += time.perf_counter() - start
        self.cache.put(key, stored)
        # what a later run replays (boxes to 0.01 px, scores to 1e-5), not the unrounded arrays: a run that
        # computes an outcome and one that replays it must score the same, to the last digit
        return Outcome.from_json(stored)

    def _render(self, world: World, fid: FrameId) -> Frame:
        key = (world_key(world), fid.key())
        frame = self._frames.get(key)
        if frame is None:
            frame = render(world, fid)
            self._frames[key] = frame
            while len(self._frames) > 16:
                self._frames.popitem(last=False)
        return frame

    def _compute(self, world: World, ids: dict[str, FrameId], before: dict[str, FrameId],
                 attribute: bool, rgb_size: tuple[int, int] | None) -> Outcome:
        frames = {m: self._render(world, fid) for m, fid in ids.items()}
        prev = {m: self._render(world, fid) for m, fid in before.items()}
        return detect(self.detector, frames, prev, attribute, rgb_size)

    # the hooks a rollout uses to reach its scenes (a recorded log provides the same ones)
    def world(self, piece: Any, simulation: Any) -> World:
        """The world of one piece (its duration is left out, see ``rollout.WORLD_SEGMENT_S``)."""
        key = (piece.scenario, piece.seed)
        world = self._worlds.get(key)
        if world is None:
            sim = simulation.model_copy(update={"scenarios": [piece.scenario], "scenario_duration_s": WORLD_SEGMENT_S,
                                                "loop": False, "seed": None})
            world = self._worlds[key] = World(SimulationConfig.model_validate(sim.model_dump()), piece.seed)
        return world

    def static(self, piece: Any) -> bool:
        """True when nobody moves in the piece's scenario (frames then use noise slots)."""
        return not SPECS[piece.scenario].moving

    def truth(self, world: World, t: float, resolution: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
        return truth(world, t, resolution)

    def imu(self, world: World, t: float) -> np.ndarray:
        return imu_frame(world, t).data


def rgb_canvas(configs: Mapping[str, SensorConfig], inputs: Collection[str]) -> tuple[int, int] | None:
    """The RGB camera's size where ``inputs`` hold no RGB frame (its boxes are drawn there); else None."""
    rgb = configs.get("rgb")
    if "rgb" in inputs or rgb is None or rgb.resolution is None:
        return None
    return (rgb.resolution[0], rgb.resolution[1])


def canvas_parts(rgb_size: tuple[int, int] | None) -> list[str]:
    """What an outcome's cache key adds for ``rgb_canvas``: nothing where an RGB frame sets the grid."""
    return [f"canvas {rgb_size[0]}x{rgb_size[1]}"] if rgb_size else []


def detect(detector: Any, frames: dict[str, Frame], previous: dict[str, Frame], attribute: bool,
           rgb_size: tuple[int, int] | None = None) -> Outcome:
    """Run the detector on ``frames`` and take the scene features the controller's state needs.

    ``previous``: each imager's frame before the current one (the motion cue compares them);
    ``rgb_size``: the RGB camera's size where ``frames`` hold no RGB frame (``rgb_canvas``).
    """
    if attribute:  # a fresh score per call: the decay between calls is the rollout's job
        detector.reset_scene_scores()
    percept = detector.infer(frames, attribute, rgb_size=rgb_size)
    boxes = np.array([d.box for d in percept.detections], dtype=np.float32).reshape(-1, 4)
    scores = np.array([d.confidence for d in percept.detections], dtype=np.float32)
    fresh = percept.contributions if attribute and percept.detections else None
    extractor = FeatureExtractor()  # the daemon's own: previous frames first, for the motion cue
    before = {m: f for m, f in previous.items() if m in frames and f.seq != frames[m].seq}
    if before:
        extractor.sample(_percept(before))
    sample = extractor.sample(_percept(frames))
    return Outcome(boxes, scores, percept.conf_agg, fresh, sample.luminance, sample.motion_image, sample.radar_points)


def _percept(frames: dict[str, Frame]) -> Percept:
    t = max(f.t for f in frames.values())
    return Percept(t, (), 0.0, None, 0.0, Bundle(t, frames, _GOOD_SYNC))  # type: ignore[arg-type]
