"""OpenVINO: the exported parts compiled for its CPU (or an Intel GPU) plug-in.

``perception.device``: ``cpu`` (the default), ``gpu`` / ``gpu:N`` (OpenVINO's GPU, GPU.N).
``precision`` is OpenVINO's inference precision: ``f32`` (what the equality tests hold it
to), ``bf16`` where the CPU has it (AVX-512 BF16 or AMX: about half the f32 time on such a
CPU, at the accuracy docs/PERFORMANCE.md measures), ``f16`` on a GPU or a CPU with FP16.
OpenVINO's CPU plug-in picks bf16 by itself on such CPUs; the hint is always set, so the
profile decides. Threads are not pinned to cores: the daemon shares its CPU.

``import openvino`` also imports its model-conversion tools, whose import sends a usage event
to Intel's telemetry unless the user opted out (a thread posting to Google Analytics). The
runtime needs only the Core, which reads ONNX itself: ``load_openvino`` imports the package
with the conversion tools held back, so a robot's detector sends nothing.
"""

from __future__ import annotations

import sys
from pathlib import Path
from types import ModuleType
from typing import Any

import torch

from respecd.errors import ConfigError
from respecd.perception.config import PerceptionConfig

NAME = "openvino"
CAPABILITY = {"f32": "FP32", "bf16": "BF16", "f16": "FP16"}  # OPTIMIZATION_CAPABILITIES of a device
CONVERSION_TOOLS = "openvino.tools.ovc"  # imported by openvino/__init__ under `except ImportError: pass`


def load_openvino() -> ModuleType:
    """``import openvino`` without its conversion tools (and their telemetry): see the module doc."""
    held = CONVERSION_TOOLS not in sys.modules
    if held:
        sys.modules[CONVERSION_TOOLS] = None  # type: ignore[assignment]  # makes its import raise ImportError
    try:
        import openvino
    finally:
        if held and sys.modules.get(CONVERSION_TOOLS, ...) is None:
            del sys.modules[CONVERSION_TOOLS]  # a later explicit import works as usual
    return openvino


def parse_device(device: str) -> str:
    """``perception.device`` -> OpenVINO's device name (CPU, GPU, GPU.N); ConfigError for anything else."""
    kind, colon, index = device.partition(":")
    if kind == "cpu" and not colon:
        return "CPU"
    if kind == "gpu" and (not colon or index.isdigit()):
        return "GPU" + (f".{index}" if index else "")
    raise ConfigError(f"perception.device: {device!r} is not a device of runtime openvino "
                      "(expected cpu, gpu or gpu:N)")


def problem(config: PerceptionConfig) -> str | None:
    """Why this OpenVINO cannot run ``config``'s device and precision, or None."""
    try:
        openvino = load_openvino()
    except ImportError as err:
        return f"runtime openvino is not installed ({err}): pip install 'respecd[openvino]'"
    try:
        device = parse_device(config.device)
    except ConfigError as err:
        return str(err).removeprefix("perception.device: ")
    core = openvino.Core()
    if device not in core.available_devices and not (device == "GPU" and "GPU.0" in core.available_devices):
        return f"device {config.device}: OpenVINO sees {', '.join(core.available_devices) or 'no device'}"
    capabilities = core.get_property(device, "OPTIMIZATION_CAPABILITIES")
    if CAPABILITY[config.precision] not in capabilities:
        return f"precision {config.precision}: OpenVINO's {device} offers {', '.join(capabilities)}"
    return None


class OpenVinoEngine:
    """One compiled model per exported part; ``engine(name, *tensors)`` runs it."""

    def __init__(self, config: PerceptionConfig, folder: Path, manifest: dict[str, Any]) -> None:
        core = load_openvino().Core()
        device = parse_device(config.device)
        properties: dict[str, Any] = {"INFERENCE_PRECISION_HINT": config.precision, "PERFORMANCE_HINT": "LATENCY"}
        if device == "CPU":
            properties.update({"INFERENCE_NUM_THREADS": config.torch_threads, "ENABLE_CPU_PINNING": False})
        self.requests: dict[str, Any] = {}
        for name, graph in manifest["graphs"].items():
            compiled = core.compile_model(core.read_model(str(folder / graph["file"])), device, properties)
            self.requests[name] = compiled.create_infer_request()

    def __call__(self, name: str, *inputs: torch.Tensor) -> tuple[torch.Tensor, ...]:
        request = self.requests[name]
        arrays = [t.detach().cpu().contiguous().numpy() for t in inputs]
        outputs = request.infer(arrays)  # copies: the request's buffers are reused by its next call
        return tuple(torch.from_numpy(outputs[port]) for port in request.model_outputs)


def load(config: PerceptionConfig, folder: Path, manifest: dict[str, Any]) -> OpenVinoEngine:
    reason = problem(config)
    if reason is not None:
        raise ConfigError(f"perception.runtime: {reason}")
    return OpenVinoEngine(config, folder, manifest)
