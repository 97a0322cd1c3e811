"""ONNX Runtime: the exported parts on its CPU, CUDA or TensorRT execution provider.

``perception.device`` picks the provider: ``cpu`` the CPU provider (MLAS; the default),
``cuda`` / ``cuda:N`` the CUDA provider on GPU N, ``tensorrt`` / ``tensorrt:N`` the TensorRT
provider with CUDA and CPU behind it for what TensorRT does not take. TensorRT compiles an
engine per input shape (kept in the export folder's ``tensorrt/``, so only the first start
pays); the head's crops, whose shape changes with every attribution, run on CUDA instead.
``precision: f16`` is TensorRT's FP16 mode; the CPU and CUDA providers run f32. The CPU provider
loads a part's ``nchwc`` graph where the export has one (``blocked.py``); the GPU providers and
OpenVINO, whose layouts the zero-padded channels would only slow, load the plain one.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from respecd.errors import ConfigError
from respecd.perception.config import PerceptionConfig
from respecd.perception.export import NCHWC

NAME = "onnxruntime"
CPU = "CPUExecutionProvider"
CUDA = "CUDAExecutionProvider"
TENSORRT = "TensorrtExecutionProvider"
CROPS = "head"  # parts run on the head's crops (FusionNet.fuse_window): a new shape every attribution
Provider = str | tuple[str, dict[str, str]]


def parse_device(device: str) -> tuple[str, int]:
    """``perception.device`` -> (cpu | cuda | tensorrt, GPU index); ConfigError for anything else."""
    kind, colon, index = device.partition(":")
    if kind in ("cpu", "cuda", "tensorrt") and (not colon or (index.isdigit() and kind != "cpu")):
        return kind, int(index or 0)
    raise ConfigError(f"perception.device: {device!r} is not a device of runtime onnxruntime "
                      "(expected cpu, cuda, cuda:N, tensorrt or tensorrt:N)")


def providers(device: str, folder: Path, precision: str = "f32", crops: bool = False) -> list[Provider]:
    """The execution providers for ``device``, in ONNX Runtime's order of preference."""
    kind, index = parse_device(device)
    if kind == "cpu":
        return [CPU]
    cuda: Provider = (CUDA, {"device_id": str(index)})
    if kind == "cuda" or crops:
        return [cuda, CPU]
    trt = {"device_id": str(index), "trt_fp16_enable": str(precision == "f16"), "trt_engine_cache_enable": "True",
           "trt_engine_cache_path": str(folder / "tensorrt")}
    return [(TENSORRT, trt), cuda, CPU]


def graph_file(graph: dict[str, Any], chosen: list[Provider]) -> str:
    """The file of an exported part these providers run: its ``nchwc`` variant on the CPU provider alone."""
    return graph.get(NCHWC, graph["file"]) if chosen == [CPU] else graph["file"]


def problem(config: PerceptionConfig) -> str | None:
    """Why this ONNX Runtime cannot run ``config``'s device and precision, or None."""
    try:
        import onnxruntime
    except ImportError as err:
        return f"runtime onnxruntime is not installed ({err}): pip install 'respecd[onnx]'"
    try:
        kind, _ = parse_device(config.device)
    except ConfigError as err:
        return str(err).removeprefix("perception.device: ")
    if config.precision != "f32" and not (kind == "tensorrt" and config.precision == "f16"):
        return (f"precision {config.precision} on device {config.device}: onnxruntime runs f32 here "
                "(f16 only on tensorrt; bf16 with runtime openvino)")
    wanted = {"cpu": CPU, "cuda": CUDA, "tensorrt": TENSORRT}[kind]
    available = onnxruntime.get_available_providers()
    if wanted not in available:
        return (f"device {config.device}: this onnxruntime {onnxruntime.__version__} has no {wanted} "
                f"(it has {', '.join(available)}; on a Jetson install NVIDIA's onnxruntime-gpu wheel)")
    return None


class OnnxRuntimeEngine:
    """One inference session per exported part; ``engine(name, *tensors)`` runs it."""

    def __init__(self, config: PerceptionConfig, folder: Path, manifest: dict[str, Any]) -> None:
        import onnxruntime as ort

        options = ort.SessionOptions()
        options.intra_op_num_threads = config.torch_threads
        options.inter_op_num_threads = 1
        options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
        options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL  # incl. NCHWc convolutions
        options.add_session_config_entry("session.intra_op.allow_spinning", "0")  # a shared CPU: no busy-waiting
        options.log_severity_level = 3  # errors only: the daemon's own log says what was loaded
        self.sessions: dict[str, tuple[Any, list[str]]] = {}
        for name, graph in manifest["graphs"].items():
            chosen = providers(config.device, folder, config.precision, crops=name.startswith(CROPS))
            session = ort.InferenceSession(str(folder / graph_file(graph, chosen)), options, providers=chosen)
            self.sessions[name] = (session, list(graph["inputs"]))

    def __call__(self, name: str, *inputs: torch.Tensor) -> tuple[torch.Tensor, ...]:
        session, names = self.sessions[name]
        feeds = {n: t.detach().cpu().contiguous().numpy() for n, t in zip(names, inputs, strict=True)}
        return tuple(torch.from_numpy(out) for out in session.run(None, feeds))


def load(config: PerceptionConfig, folder: Path, manifest: dict[str, Any]) -> OnnxRuntimeEngine:
    reason = problem(config)
    if reason is not None:
        raise ConfigError(f"perception.runtime: {reason}")
    return OnnxRuntimeEngine(config, folder, manifest)
