"""The fusion detector behind a synchronous ``infer(frames, attribute) -> Percept``.

``infer`` is called from one worker thread (see ``stage.py``); it aligns the bundle's
frames into the RGB view, runs the network at the RGB frame's own resolution (padded to
a multiple of 32), applies NMS and, when asked, attributes the top detections to the
input channels. It never raises for a missing modality: that channel is zero and its
presence flag 0.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import structlog
import torch

from respecd.errors import ConfigError
from respecd.messages import Detection, Frame, Percept, conf_agg
from respecd.perception import checkpoint, fold, split
from respecd.perception.align import AlignedInput, Aligner
from respecd.perception.attribution import Attribution, Attributor, SceneScores
from respecd.perception.boxes import postprocess
from respecd.perception.calibration import ScoreCalibration
from respecd.perception.checkpoint import Net
from respecd.perception.config import PerceptionConfig
from respecd.perception.model import count_parameters
from respecd.perception.parts import Engine
from respecd.sensors import Calibration

log = structlog.get_logger(__name__)

EXPORTS = "exported"  # the state directory's folder of exported graphs (``export.cached``)


@dataclass(frozen=True)
class Inference:
    """``FusionDetector.run``'s answer: the detections and, when attributed, the scene's numbers per modality."""

    detections: tuple[Detection, ...]
    contributions: dict[str, float] | None = None  # the held scene score (``SceneScores``)
    dependence: dict[str, float] | None = None  # this frame's, None without a detection to attribute
    sufficiency: dict[str, float] | None = None


class FusionDetector:
    """Aligner + FusionNet + NMS + attribution, with the scene score kept between calls."""

    def __init__(self, model: Net, config: PerceptionConfig,
                 calibration: dict[str, Calibration | None] | None = None) -> None:
        self.config = config
        self.device = self.torch_device(config)
        for p in model.parameters():  # attribution needs input gradients only
            p.requires_grad_(False)
        self.parameters = count_parameters(model)  # as trained (folding merges each batch norm into a conv)
        self.model = fold.for_inference(model, self.device)  # the daemon never trains its detector
        self.channels = model.spec.channels
        self.aligner = Aligner(config, calibration)
        self.split = split.as_split(self.model)  # the net's stages (split.py): every forward runs through them
        self.attributor = Attributor(self.model, config.attribution_method, config.attribution_sufficiency)
        self.scores = self.scene_scores()

    @classmethod
    def load(cls, config: PerceptionConfig, calibration: dict[str, Calibration | None] | None = None,
             exports: Path | None = None) -> FusionDetector:
        """Load ``config.weights`` (``builtin:NAME`` or a path); ConfigError if bad or mismatched.

        With ``runtime`` onnxruntime or openvino the net's parts run there, exported into ``exports``
        (default: ``exported/`` in the default state directory) on first use."""
        if config.runtime != "torch":
            from respecd.perception import runtimes

            reason = runtimes.problem(config)  # before loading or exporting anything
            if reason is not None:
                raise ConfigError(f"perception.runtime: {reason}")
        device = str(cls.torch_device(config))
        model, payload = checkpoint.load(config.weights, expected=config.model, map_location=device)
        if payload.get("score_calibration") is not None:  # confidences that mean the same at every RGB size
            model.score_calibration = ScoreCalibration.from_payload(payload["score_calibration"], config.weights)
        log.info("detector_loaded", weights=config.weights, channels=",".join(model.spec.channels),
                 trained_on=payload.get("data"))
        detector = cls(model, config, calibration)
        if config.runtime != "torch":
            detector.model.engine = detector.exported_engine(exports)
        return detector

    @staticmethod
    def torch_device(config: PerceptionConfig) -> torch.device:
        """Where torch holds the net: ``device`` for runtime torch; the CPU beside another runtime (its glue)."""
        return torch.device(config.device if config.runtime == "torch" else "cpu")

    def exported_engine(self, exports: Path | None) -> Engine:
        """The net exported (cached by checkpoint hash) and loaded into the profile's runtime."""
        from respecd.perception import export, runtimes

        if exports is None:
            from respecd.control.persist import resolve_state_dir

            exports = resolve_state_dir(None) / EXPORTS
        folder = export.cached(self.model, checkpoint.resolve(self.config.weights), exports, self.config.weights)
        return runtimes.load(self.config, folder, export.read_manifest(folder, self.model.spec))

    def scene_scores(self) -> SceneScores:
        """A fresh held scene score for this detector's channels and attribution method."""
        per_channel = self.config.attribution_method == "gradient"
        return SceneScores(self.channels, self.config.attribution_decay_s, per_channel)

    def reset_scene_scores(self) -> None:
        """Forget the decaying scene score: the next attribution stands on its own (an
        offline evaluator scores each call alone and applies the decay itself)."""
        self.scores = self.scene_scores()

    def start_session(self) -> None:
        """Forget what an earlier session on this detector left: its scene score and RGB frame size."""
        self.reset_scene_scores()
        self.aligner.forget_rgb_size()

    def first_rgb_size(self) -> tuple[int, int]:
        """The grid of a bundle without RGB before any RGB frame (``Aligner.first_rgb_size``)."""
        return self.aligner.first_rgb_size()

    def prepare(self, frames: dict[str, Frame], rgb_size: tuple[int, int] | None = None) -> AlignedInput:
        """The network's input for ``frames`` (decoded, aligned, normalised): all ``infer`` does before
        the network; without an RGB frame, on ``rgb_size`` or the last RGB frame's grid (``Aligner.align``).
        Raises what decoding raises."""
        return self.aligner.align(frames, rgb_size)

    def infer(self, frames: dict[str, Frame], attribute: bool, aligned: AlignedInput | None = None,
              rgb_size: tuple[int, int] | None = None) -> Percept:
        """Detections (+ contributions when ``attribute``) for one set of synchronized frames.

        ``aligned``: ``prepare(frames)`` done already (a replay prepares the next bundle while
        this detector runs on the current one); None: prepared here. ``rgb_size``: see ``prepare``."""
        start = time.perf_counter()
        if aligned is None:
            aligned = self.prepare(frames, rgb_size)
        t = max((f.t for f in frames.values()), default=0.0)
        result = self.run(aligned, attribute, t)
        return Percept(
            t=t,
            detections=result.detections,
            conf_agg=conf_agg([d.confidence for d in result.detections]),
            contributions=result.contributions,
            latency=time.perf_counter() - start,
            dependence=result.dependence,
            sufficiency=result.sufficiency,
        )

    def run(self, aligned: AlignedInput, attribute_now: bool, t: float = 0.0) -> Inference:
        """Network + NMS (+ attribution) on an aligned input."""
        x = torch.from_numpy(aligned.tensor).unsqueeze(0).to(self.device)  # (1, C, Hp, Wp)
        if getattr(self.model, "engine", None) is None:  # torch runs the net (any net, not only ours)
            x = fold.channels_last(x)  # the layout for_inference put torch's net in
        presence = torch.from_numpy(aligned.presence).unsqueeze(0).to(self.device)  # (1, A)
        cfg = self.config
        if not attribute_now:
            with torch.inference_mode():
                boxes, scores = split.forward(self.split, x, presence)
                dets = postprocess(boxes, scores, tuple(x.shape[2:]), cfg.score_threshold, cfg.iou_threshold,
                                   cfg.max_detections)[0]
            return Inference(self._detections(dets, None, aligned.size))
        result = self.attributor(x, presence, cfg.score_threshold, cfg.iou_threshold, cfg.max_detections,
                                 cfg.attribution_targets)
        contributions = self.scores.update(t, result.scene)
        return Inference(self._detections(result.detections, result, aligned.size), contributions,
                         result.dependence, result.sufficiency)

    def _detections(self, dets, attribution: Attribution | None, size: tuple[int, int]) -> tuple[Detection, ...]:
        boxes, scores, labels, _ = dets
        shares = attribution.shares if attribution is not None else None
        w, h = size
        boxes = boxes.detach().cpu().numpy()
        boxes = np.clip(boxes, 0, [w, h, w, h])  # letterbox padding is bottom/right: only clipping needed
        names = self.model.spec.classes
        out = []
        for i in range(len(scores)):
            contrib = None
            if attribution is not None and shares is not None and i < len(shares):
                contrib = dict(zip(attribution.modalities, shares[i].tolist(), strict=True))
            x1, y1, x2, y2 = (float(v) for v in boxes[i])
            out.append(Detection(box=(x1, y1, x2, y2), confidence=float(scores[i]),
                                 label=names[int(labels[i])], contributions=contrib))
        return tuple(out)


def frames_from_arrays(rgb: np.ndarray | None, thermal: np.ndarray | None = None, radar: np.ndarray | None = None,
                       depth: np.ndarray | None = None, t: float = 0.0) -> dict[str, Frame]:
    """Convenience for tools and tests: wrap raw arrays as Frames by modality."""
    frames: dict[str, Frame] = {}
    for name, data in (("rgb", rgb), ("thermal", thermal), ("radar", radar), ("depth", depth)):
        if data is not None:
            frames[name] = Frame(modality=name, t=t, seq=0, data=data)  # type: ignore[arg-type]
    return frames
