"""Profile section ``perception:``.

``model`` describes the network's shape; it must match the checkpoint (the loader says
which field differs). The defaults are the shipped ``builtin:sim-rover`` checkpoint.
"""

from __future__ import annotations

import re
from importlib import resources
from pathlib import Path
from typing import Literal

from pydantic import Field, model_validator

from respecd.errors import ConfigError
from respecd.sensors import StrictModel

AuxModality = Literal["thermal", "radar", "depth"]
BUILTIN_PREFIX = "builtin:"
_BUILTIN_NAME = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]*")  # a file of the package, never a path out of it


def resolve_weights(source: str) -> Path:
    """'builtin:NAME' -> the packaged weights file; anything else is a path (no torch needed)."""
    if not source.startswith(BUILTIN_PREFIX):
        return Path(source)
    name = source[len(BUILTIN_PREFIX):]
    if not _BUILTIN_NAME.fullmatch(name):
        raise ConfigError(f"{source}: a built-in checkpoint is named by a plain name (no '/' or '..'), got {name!r}")
    resource = resources.files("respecd.perception") / "weights" / f"{name}.pt"
    with resources.as_file(resource) as path:
        if not path.is_file():
            raise ConfigError(f"{source}: no built-in checkpoint named {name!r} (run `make weights`)")
        return Path(path)


class ModelSpec(StrictModel):
    """Shape of the two-backbone fusion detector (see ``respecd/perception/model.py``).

    Widths are per stage P1..P5 of each backbone (YOLOv8n uses 16, 32, 64, 128, 256 for
    one backbone). The default is narrower, so that two backbones plus neck train on a
    2-core CPU in under 30 minutes and run 640x360 within the 120 ms budget.
    """

    backbone: str = Field(
        "csp",
        pattern=r"^(csp|darknet:[A-Za-z0-9_.-]+)$",
        description="'csp': the YOLOv8-style net (widths below); 'darknet:NAME': two copies of the backbone of the "
        "Darknet cfg NAME shipped in respecd/perception/cfg/ (pretrained weights imported), fused at the inputs of "
        "its yolo head (widths, depths and reg_max below are then unused).",
    )
    aux_backbone: str | None = Field(
        None,
        pattern=r"^darknet:[A-Za-z0-9_.-]+$",
        description="Darknet backbone only: backbone 2 from another packaged cfg (e.g. a wider one on thermal) than "
        "backbone 1 and the head; its features reach the head through the learned fusion convolutions. "
        "None: the same cfg as 'backbone'.",
    )
    aux_scale: float = Field(
        1.0,
        gt=0.1,
        le=1.0,
        description="Darknet backbone only: backbone 2 sees the aligned aux planes resized by this factor (a "
        "160x120 thermal camera upsampled into the RGB view holds no more detail at 0.5), and its features "
        "are resized back to backbone 1's: a quarter of the cost at 0.5.",
    )
    rgb_aware_fusion: bool = Field(
        False,
        description="Darknet backbone only: backbone 2's evidence has one 1x1 map while the RGB image is black (W_aux: "
        "the aux sensors alone) and another while it is not (W_both), both started as W_aux starts, so that the aux "
        "sensors alone and beside an RGB camera that also sees are trained (or kept) apart.",
    )
    aux_modalities: tuple[AuxModality, ...] = Field(
        ("thermal", "radar"),
        description="Non-RGB channels fed to backbone 2, in order (depth optional as a sixth channel).",
    )
    rgb_widths: tuple[int, int, int, int, int] = Field(
        (16, 24, 48, 96, 128), description="Backbone 1 (RGB) channel widths at strides 2, 4, 8, 16, 32."
    )
    aux_widths: tuple[int, int, int, int, int] = Field(
        (8, 16, 32, 64, 96), description="Backbone 2 (thermal, radar, depth) widths at strides 2, 4, 8, 16, 32."
    )
    neck_widths: tuple[int, int, int] = Field(
        (48, 96, 128), description="Fused feature widths of the FPN/PAN neck at P3, P4, P5."
    )
    depths: tuple[int, int, int, int] = Field(
        (1, 1, 1, 1), description="C2f bottleneck repeats at strides 4, 8, 16, 32 (YOLOv8n: 1, 2, 2, 1)."
    )
    reg_max: int = Field(16, ge=1, le=32, description="DFL bins per box side (YOLOv8: 16).")
    classes: tuple[str, ...] = Field(("person",), min_length=1, description="Class names, index order.")

    @property
    def channels(self) -> tuple[str, ...]:
        """Names of the input channels in tensor order."""
        return ("r", "g", "b", *self.aux_modalities)


class PerceptionConfig(StrictModel):
    enabled: bool = Field(True, description="Run the detector; off leaves the controller on scene signals only.")
    weights: str = Field(
        "builtin:sim-rover",
        description="Checkpoint path, or 'builtin:NAME' for a checkpoint shipped inside the package.",
    )
    device: str = Field(
        "cpu",
        description="Where the detector runs. runtime torch: a torch device (cpu, cuda, cuda:N); onnxruntime: cpu, "
        "cuda, cuda:N (its CUDA provider), tensorrt, tensorrt:N (its TensorRT provider); openvino: cpu, gpu, gpu:N.",
    )
    runtime: Literal["torch", "onnxruntime", "openvino"] = Field(
        "torch",
        description="What runs the network: torch, or the checkpoint exported to ONNX (once, cached in the state "
        "directory by checkpoint hash) and run by ONNX Runtime (pip install 'respecd[onnx]') or OpenVINO "
        "('respecd[openvino]'). Same detections and contributions in f32; see docs/PERFORMANCE.md.",
    )
    precision: Literal["f32", "bf16", "f16"] = Field(
        "f32",
        description="Inference precision: f32 everywhere; bf16 with runtime openvino on a CPU that has it; f16 with "
        "openvino on a GPU or onnxruntime on tensorrt. Lower precision moves mAP: docs/PERFORMANCE.md.",
    )
    score_threshold: float = Field(0.25, ge=0, le=1, description="Minimum confidence kept after NMS.")
    iou_threshold: float = Field(0.5, gt=0, le=1, description="NMS IoU above which the weaker box is suppressed.")
    max_detections: int = Field(50, ge=1, le=1000, description="Detections kept per frame after NMS.")
    attribution_every_s: float = Field(
        1.0, gt=0, description="Seconds between contribution attributions (default: once per decision)."
    )
    attribution_method: Literal["ablation", "gradient"] = Field(
        "ablation",
        description="Contribution method: 'ablation' (confidence lost with each sensor off; faithful, about 2x a "
        "forward) or 'gradient' (the paper's gradient x input; one backward pass). See docs/PERCEPTION.md.",
    )
    attribution_sufficiency: Literal["auto", "always"] = Field(
        "auto",
        description="ablation: each sensor's sufficiency (the confidence it keeps alone) is free with two sensors "
        "on; with more, 'always' runs one more fusion pass per sensor for it, 'auto' leaves it out. See "
        "docs/PERCEPTION.md.",
    )
    attribution_targets: int = Field(
        5, ge=1, le=50, description="Top detections whose confidences are attributed to the input channels."
    )
    attribution_decay_s: float = Field(
        3.0, gt=0, description="Time constant (s) of the decay toward uniform scores while nothing is detected."
    )
    torch_threads: int = Field(
        1,
        ge=1,
        le=64,
        description="Intra-op threads for inference (torch's, or the runtime's); 1 leaves the second core to the "
        "event loop and drivers.",
    )
    thermal_range_k: tuple[float, float] = Field(
        (273.0, 313.0), description="Kelvin mapped to 0..1 for thermal frames in kelvin (meta units 'K')."
    )
    thermal_counts_per_k: float = Field(
        100.0,
        gt=0,
        description="Raw uint16 thermal counts per kelvin (counts = K x this; the simulator's centikelvin).",
    )
    plane_depth_m: float = Field(
        5.0, gt=0, description="Depth (m) of the plane the thermal homography is exact for (parallax elsewhere)"
    )
    radar_max_range_m: float = Field(15.0, gt=0, description="Radar points farther than this are not projected.")
    depth_max_m: float = Field(10.0, gt=0, description="Depth mapped to 0..1 over 0..this many metres.")
    model: ModelSpec = Field(ModelSpec(), description="Network shape; must match the checkpoint.")

    @model_validator(mode="after")
    def _precision_needs_a_runtime(self) -> PerceptionConfig:
        if self.precision != "f32" and self.runtime == "torch":
            raise ValueError(f"precision {self.precision} needs runtime onnxruntime or openvino (torch runs f32)")
        return self

    @model_validator(mode="after")
    def _gradient_needs_torch(self) -> PerceptionConfig:
        if self.attribution_method == "gradient" and self.runtime != "torch":
            raise ValueError(f"attribution_method gradient needs runtime torch: an exported {self.runtime} graph "
                             "has no gradients (ablation runs through any runtime)")
        return self

    @model_validator(mode="after")
    def _ordered_thermal_range(self) -> PerceptionConfig:
        if self.thermal_range_k[0] >= self.thermal_range_k[1]:
            raise ValueError("thermal_range_k must be (low, high) with low < high")
        return self
