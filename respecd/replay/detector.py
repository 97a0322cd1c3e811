"""Which detector a replay runs, on which device, and how its report names them.

A replay studies a robot's session wherever the log is opened: a profile written for the
Jetson (``device: cuda``) replays on a laptop's CPU. The live daemon refuses a device it
cannot use (``respecd.preflight``: its latency and load would describe another machine); a
replay runs the detector on the CPU instead and says so once in the log and in the report.
A profile's ``perception.runtime`` (ONNX Runtime on TensorRT, OpenVINO on a GPU) runs here on
the CPU in f32 when that runtime is installed, else through torch on the CPU.
A lockstep replay's latencies are modelled from the log, so the controller decides as it
would have on the robot whichever device runs the detector here.

A ROS bag's camera images replayed without a profile run the default profile's detector,
which was trained on the simulator: the first log line and the report say so, and how to
choose a detector for real images.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import TYPE_CHECKING, Any

import structlog

from respecd.errors import ConfigError

if TYPE_CHECKING:
    from respecd.perception.config import PerceptionConfig

log = structlog.get_logger(__name__)

REAL_IMAGES_HINT = ("for real camera images pass --profile builtin:spec-rover (builtin:rgbt: real-photo RGB and "
                    "thermal backbones) or a profile naming your own checkpoint in perception.weights")
CAMERAS = ("rgb", "thermal")
PLACEMENT = {"runtime": "torch", "device": "cpu", "precision": "f32"}  # perception's fields and defaults


def usable_device(requested: str) -> tuple[str, str | None]:
    """The torch device a replay runs the detector on: ``requested`` when this machine can use
    it, else ``cpu`` and why not."""
    from respecd.preflight import NOT_A_DEVICE, device_problem

    problem = device_problem(requested)
    if problem and NOT_A_DEVICE in problem:  # a typo, not this machine: wrong on the robot too
        raise ConfigError(f"perception.device: {problem}")
    return ("cpu", problem) if problem else (requested, None)


def usable_runtime(section: dict[str, Any]) -> tuple[dict[str, str], str | None]:
    """(runtime, device, precision) a replay runs a non-torch ``perception.runtime`` with: the
    profile's when this machine has them, else that runtime on the CPU in f32, else torch on the
    CPU (same detections in f32: docs/DEPLOY.md), and why. A device the runtime never names is a
    profile error."""
    from respecd.perception.config import PerceptionConfig
    from respecd.perception.runtimes import backend, problem

    wanted = {k: str(section.get(k, d)) for k, d in PLACEMENT.items()}
    backend(wanted["runtime"]).parse_device(wanted["device"])  # ConfigError: wrong on the robot too
    try:
        config = PerceptionConfig.model_validate(section)
    except ValueError:
        return wanted, None  # the profile's own validation says what is wrong
    why = problem(config)
    if why is None:
        return wanted, None
    on_cpu = {**wanted, "device": "cpu", "precision": "f32"}
    if problem(config.model_copy(update=on_cpu)) is None:
        return on_cpu, why
    return {"runtime": "torch", "device": "cpu", "precision": "f32"}, why


def placement(section: dict[str, Any]) -> tuple[dict[str, str], str | None]:
    """What the detector runs with here (runtime, device, precision) and why it differs from the
    profile's (None when it does not)."""
    wanted = {k: str(section.get(k, d)) for k, d in PLACEMENT.items()}
    if wanted["runtime"] != "torch":
        return usable_runtime(section)
    device, why = usable_device(wanted["device"])
    return {**wanted, "device": device}, why


def place(perception: dict[str, Any] | None) -> dict[str, Any]:
    """The profile's ``perception`` section with a runtime and device this machine can use
    (logged once when they differ from the profile's)."""
    section = dict(perception or {})
    if not section.get("enabled", True):
        return section
    chosen, why = placement(section)
    if why is not None:
        profile = {f"profile_{k}": str(section.get(k, d)) for k, d in PLACEMENT.items()}
        log.warning("replay.device", **profile, **chosen, reason=why,
                    note="the detector runs on this machine's CPU; a lockstep replay's latencies are "
                         "modelled from the log, so the decisions do not change")
        section.update(chosen)
    return section


def provenance(config: str | Path | dict[str, Any] | None, session: Any) -> tuple[str, bool]:
    """Who chose the detector (the profile given, the log's own, or the default one), and whether
    it is the default (simulator) detector on a ROS bag's camera images."""
    from respecd.config import DEFAULT_PROFILE

    explicit = config is not None and not (isinstance(config, (str, Path)) and str(config) in ("", DEFAULT_PROFILE))
    topic_map = getattr(session, "topic_map", None)
    if explicit:
        return (f"--profile {config}" if isinstance(config, (str, Path)) else "the profile given"), False
    if topic_map is None:
        return "the profile recorded in the log", False
    return f"the default profile {DEFAULT_PROFILE} (no --profile given)", any(m in topic_map for m in CAMERAS)


def announce(weights: str) -> None:
    """The first log line of a ROS bag's camera images replayed with the default profile."""
    log.warning("replay.detector", weights=weights, trained_on="the simulator",
                note=f"no --profile given: the default profile's detector ({weights}), trained on the simulator, "
                     "runs on this bag's camera images", hint=REAL_IMAGES_HINT)


def entry(perception: PerceptionConfig, profile_perception: dict[str, Any] | None, chosen_by: str,
          foreign: bool = False) -> dict[str, Any]:
    """The report's ``detector``: the checkpoint that ran (file, sha256, card), the runtime and
    device, who chose it, and the profile's runtime/device where the replay could not use them."""
    if not perception.enabled:
        return {"enabled": False, "chosen_by": chosen_by}
    described: dict[str, Any] = {"weights": perception.weights, "runtime": perception.runtime,
                                 "device": perception.device, "precision": perception.precision,
                                 "chosen_by": chosen_by}
    asked = profile_perception or {}
    wanted = {k: str(asked.get(k, d)) for k, d in PLACEMENT.items()}
    if any(wanted[k] != described[k] for k in PLACEMENT):
        described.update({f"profile_{k}": v for k, v in wanted.items() if v != described[k]})
        described["device_note"] = placement(asked)[1]
    described.update(_checkpoint(perception.weights))
    if foreign:
        described["note"] = "the default profile's detector, trained on the simulator, on a bag's real images"
        described["hint"] = REAL_IMAGES_HINT
    return described


def _checkpoint(weights: str) -> dict[str, Any]:
    """The checkpoint file's name and content hash, and what its card (JSON beside it) says it is."""
    from respecd.perception.config import resolve_weights

    try:
        path = resolve_weights(weights)
        digest = _sha256(path)
    except (ConfigError, OSError):
        return {}
    found: dict[str, Any] = {"checkpoint": path.name, "sha256": digest}
    card = path.with_suffix(".json")
    try:
        body = json.loads(card.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return found
    if isinstance(body, dict):
        found.update({k: body[k] for k in ("name", "parameters") if k in body})
    return found


def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with path.open("rb") as f:
        while block := f.read(1 << 20):
            digest.update(block)
    return digest.hexdigest()
