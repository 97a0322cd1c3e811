"""Runtimes besides torch that run an exported detector (``perception.runtime``).

A registry of back-ends imported only when a profile names them (python-can's interfaces):
the daemon on ``runtime: torch`` never imports ONNX Runtime or OpenVINO, and a missing one
is a one-line ConfigError naming the extra to install. Each back-end module offers
``problem(config)`` (why it cannot run here: package, device, precision) and an engine class
that runs the parts of an export folder (``respecd.perception.export``) by name; the net's
``engine`` attribute routes its parts there (``parts.py``).
"""

from __future__ import annotations

import importlib
import importlib.util
from pathlib import Path
from types import ModuleType
from typing import Any

import structlog

from respecd.errors import ConfigError
from respecd.perception.config import PerceptionConfig
from respecd.perception.parts import Engine

log = structlog.get_logger(__name__)

RUNTIMES: dict[str, str] = {  # perception.runtime -> module; "torch" is the nets' own code
    "onnxruntime": "respecd.perception.runtimes.onnxruntime",
    "openvino": "respecd.perception.runtimes.openvino",
}
EXTRAS = {"onnxruntime": "onnx", "openvino": "openvino"}  # pip install 'respecd[EXTRA]'


def backend(name: str) -> ModuleType:
    """The back-end module of runtime ``name`` (not the runtime's package: that is imported on use)."""
    if name not in RUNTIMES:
        raise ConfigError(f"perception.runtime: {name!r} is not a runtime (expected torch, {', '.join(RUNTIMES)})")
    return importlib.import_module(RUNTIMES[name])


def installed(module: str) -> bool:
    """Whether ``module`` can be imported, without importing it."""
    try:
        return importlib.util.find_spec(module) is not None
    except (ImportError, ValueError):  # ValueError: a module set to None in sys.modules (held back)
        return False


def problem(config: PerceptionConfig) -> str | None:
    """Why ``config``'s runtime, device and precision cannot run on this machine, or None (torch: None)."""
    if config.runtime == "torch":
        return None
    if not installed("onnx"):
        return (f"runtime {config.runtime} needs the onnx package to export the checkpoint (torch.onnx writes "
                f"through it): pip install 'respecd[{EXTRAS[config.runtime]}]'")
    return backend(config.runtime).problem(config)


def load(config: PerceptionConfig, folder: Path, manifest: dict[str, Any]) -> Engine:
    """An engine over the export ``folder`` for ``config``'s runtime, device, threads and precision."""
    engine: Engine = backend(config.runtime).load(config, folder, manifest)
    log.info("detector_runtime", runtime=config.runtime, device=config.device, precision=config.precision,
             graphs=",".join(manifest["graphs"]), export=str(folder))
    return engine
