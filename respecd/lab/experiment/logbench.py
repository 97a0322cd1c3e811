"""``bench scenarios --log LOG``: the same comparison, replayed counterfactually on a recorded
session instead of the simulator.

Every policy drives its own controller over the log's time line, exactly as in
``rollout.py``; what changes is where the frames come from. At an instant ``t`` a sensor
configured at ``r`` Hz hands the detector what ``respecd.replay.counterfactual`` says it
delivered by then — the rules ``respecd --replay``'s driver applies to the same log: the
first logged frame of each period of ``r`` (a higher rate than recorded cannot invent
frames), resized to the chosen resolution (above the recorded one an upscale), radar points
cut and folded to the chosen chirp mode (``radar_mode_counterfactual: true`` in the JSON).

Ground truth comes from the RGB frames' ``meta["gt"]`` (sessions recorded on the simulated
rover carry it): the newest logged RGB frame at ``t`` gives the truth at ``t``, so a
decimated, stale frame is scored against where people really are. Without it mAP is null.
Scenarios are the log's own segments (``meta["scenario"]`` of the RGB frames), or the whole
log as one piece. Outcomes are kept in memory only (a log's frames are not reproducible
from a seed), keyed by the logged frames (with each imager's previous frame, which the motion
cue compares it with) and the resolution.
"""

from __future__ import annotations

import bisect
import json
import time
from collections import OrderedDict
from typing import Any

import numpy as np

from respecd.errors import InputError
from respecd.lab.experiment.cache import OutcomeCache, outcome_key
from respecd.lab.experiment.outcomes import MOTION_IMAGERS, Outcome, canvas_parts, detect, rgb_canvas
from respecd.lab.experiment.rollout import Piece
from respecd.messages import Frame, SensorConfig
from respecd.record import codec
from respecd.record.codec import LoggedSchema
from respecd.record.reader import SessionLog, open_log
from respecd.record.topics import meta_topic, sensor_topic
from respecd.replay import counterfactual


class LogFrames:
    """One sensor per modality of a session log: encoded frames indexed by time, decoded on demand."""

    def __init__(self, session: SessionLog, modalities: tuple[str, ...]) -> None:
        self.session = session
        names: dict[str, str] = {}
        for sensor, modality in session.sensors.items():
            if modality in modalities and modality not in names.values():
                names[sensor] = modality
        topics = {sensor_topic(s): m for s, m in names.items()}
        metas = {meta_topic(s): m for s, m in names.items()}  # FrameMeta: just before its frame
        self.times: dict[str, list[float]] = {m: [] for m in topics.values()}
        self.records: dict[str, list[tuple[LoggedSchema, bytes, int, dict | None]]] = {m: [] for m in topics.values()}
        stashed: dict[str, tuple[int, dict]] = {}
        for topic, schema, ns, data in session.messages([*topics, *metas]):
            if topic in metas:
                stashed[metas[topic]] = (ns, json.loads(data))
                continue
            kind = topics[topic]
            meta = stashed.pop(kind, None)
            self.times[kind].append((ns - session.start_ns) / 1e9)  # seconds since the log began
            self.records[kind].append((schema, data, ns, meta[1] if meta and meta[0] == ns else None))
        if not self.times.get("rgb"):
            raise InputError(f"{session.path}: the log holds no RGB frames (the detector needs them)")
        self._decoded: OrderedDict[tuple[str, int], Frame] = OrderedDict()

    def index_at(self, modality: str, t: float) -> int | None:
        """Index of the newest frame of ``modality`` logged at or before ``t``."""
        times = self.times.get(modality) or []
        i = bisect.bisect_right(times, t + 1e-9) - 1
        return i if i >= 0 else None

    def frame(self, modality: str, index: int) -> Frame:
        key = (modality, index)
        frame = self._decoded.get(key)
        if frame is None:
            schema, data, ns, meta = self.records[modality][index]
            frame = codec.decode_frame(schema, data, modality, ns, meta)  # type: ignore[arg-type]
            frame = Frame(frame.modality, self.times[modality][index], index, frame.data, frame.meta)
            self._decoded[key] = frame
            while len(self._decoded) > 48:
                self._decoded.popitem(last=False)
        return frame

    @property
    def duration_s(self) -> float:
        return self.times["rgb"][-1]

    def segments(self) -> list[Piece]:
        """The log's scenario segments (from the RGB frames' metadata), whole seconds each."""
        marks: list[tuple[float, str]] = []
        for second in range(int(self.duration_s) + 1):
            i = self.index_at("rgb", float(second))
            if i is not None:
                name = str(self.frame("rgb", i).meta.get("scenario", "log"))
                if not marks or marks[-1][1] != name:
                    marks.append((float(second), name))
        pieces = []
        for k, (start, name) in enumerate(marks):
            end = marks[k + 1][0] if k + 1 < len(marks) else float(int(self.duration_s))
            if end - start >= 1.0:
                pieces.append(Piece(name, 0, end - start, start))
        if not pieces:
            raise InputError(f"{self.session.path}: the log is shorter than one decision period")
        return pieces


class LogEvaluator:
    """The rollout's source for a recorded session (same hooks as ``outcomes.Evaluator``)."""

    def __init__(self, detector: Any, frames: LogFrames) -> None:
        self.detector = detector
        self.frames = frames
        self.inputs = ("rgb", *detector.model.spec.aux_modalities)
        self.cache = OutcomeCache(None)
        self.fingerprint = f"log:{frames.session.path.name}"
        self.inference_s = 0.0

    def world(self, piece: Piece, simulation: Any) -> Piece:
        return piece  # a piece of the log: times are relative to its start

    def static(self, piece: Piece) -> bool:
        return False  # logged frames are all distinct

    def _pick(self, modality: str, config: SensorConfig, t: float) -> int | None:
        return counterfactual.delivered_index(self.frames.times[modality], config.rate_hz, t)

    def outcome(self, piece: Piece, configs: dict[str, SensorConfig], t: float, attribute: bool,
                slot: int | None = None) -> Outcome:
        t_log = piece.start_s + t
        picked = {m: self._pick(m, c, t_log) for m, c in configs.items()
                  if m in self.inputs and c.enabled and m in self.frames.times}
        picks = {m: i for m, i in picked.items() if i is not None}
        res = {m: configs[m].resolution for m in picks}
        earlier = {m: self._pick(m, configs[m], t_log - 1.0 / configs[m].rate_hz) for m in MOTION_IMAGERS
                   if m in picks}
        before = {m: j for m, j in earlier.items() if j is not None}
        rgb_size = rgb_canvas(configs, picks)
        parts = [f"{m}:{i}:{res[m]}:{configs[m].mode}" for m, i in picks.items()]
        parts += [f"before {m}:{j}" for m, j in before.items()]
        parts += canvas_parts(rgb_size)
        key = outcome_key(self.fingerprint, "", parts, attribute)  # the motion cue's previous frame is in the key
        cached = self.cache.get(key)
        if cached is not None:
            return Outcome.from_json(cached)
        start = time.perf_counter()
        frames = {m: self._deliver(m, i, configs[m]) for m, i in picks.items()}
        prev = {m: self._deliver(m, j, configs[m]) for m, j in before.items()}
        result = detect(self.detector, frames, prev, attribute, rgb_size)
        self.inference_s += time.perf_counter() - start
        self.cache.put(key, result.to_json())
        return result

    def _deliver(self, modality: str, index: int, config: SensorConfig) -> Frame:
        frame = counterfactual.transform(self.frames.frame(modality, index), config)
        assert frame is not None, "only enabled sensors are picked"
        return frame

    def truth(self, piece: Piece, t: float, resolution: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
        from respecd.lab.detector.data import gt_arrays

        i = self.frames.index_at("rgb", piece.start_s + t)
        frame = self.frames.frame("rgb", i) if i is not None else None
        if frame is None or "gt" not in frame.meta:
            return np.zeros((0, 4), np.float32), np.zeros(0, bool)
        boxes, ignore = gt_arrays(frame.meta["gt"])
        h, w = frame.data.shape[:2]
        return boxes * np.array([resolution[0] / w, resolution[1] / h] * 2, dtype=np.float32), ignore

    def imu(self, piece: Piece, t: float) -> np.ndarray:
        i = self.frames.index_at("imu", piece.start_s + t)
        return self.frames.frame("imu", i).data if i is not None else np.zeros(6, np.float32)


def prepare_log(args: Any, detector: Any) -> tuple:
    """The recorded session as the source: its scenario segments, its own frames for timing."""
    session = open_log(args.log)
    frames = LogFrames(session, ("rgb", "thermal", "radar", "depth", "imu"))
    evaluator = LogEvaluator(detector, frames)
    pieces = frames.segments()
    limit = args.duration or (4.0 if args.quick else None)
    if limit:
        pieces = [Piece(p.scenario, p.seed, min(p.duration_s, limit), p.start_s) for p in pieces]
    middle = frames.duration_s / 2

    def frames_for(res: tuple[int, int]) -> dict[str, Frame]:
        picks = {m: frames.index_at(m, middle) for m in evaluator.inputs if m in frames.times}
        return {m: counterfactual.resize(frames.frame(m, i), res) if m == "rgb" else frames.frame(m, i)
                for m, i in picks.items() if i is not None}

    extra = {"log": str(args.log), "log_duration_s": round(frames.duration_s, 2), "radar_mode_counterfactual": True,
             "ground_truth": "gt" in frames.frame("rgb", 0).meta}
    return evaluator, pieces, frames_for, extra
