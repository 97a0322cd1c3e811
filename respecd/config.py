"""The profile: one YAML file describing sensors, synchronizer, perception, controller,
recording and telemetry, validated by pydantic. A profile may be an overlay of another
(``extends:``, resolved by ``respecd.profile_overlay``).

Errors come back as ``FILE:LINE: field.path: message (expected ...)``, one per problem,
because a robotics engineer editing YAML on a rover needs the line, not a traceback.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal, Union

from pydantic import Field, ValidationError, model_validator

# the driver modules import their hardware SDKs only when a sensor starts (pyrealsense2, pyusb, cv2
# capture), so these imports are cheap and a profile without a RealSense loads without pyrealsense2
from respecd.control.config import ControllerConfig
from respecd.drivers import DRIVERS
from respecd.drivers.flirone import FlirOneConfig
from respecd.drivers.iwr6843 import IWR6843Config
from respecd.drivers.realsense import RealSenseConfig
from respecd.drivers.replay import ReplayConfig
from respecd.drivers.sim import SimConfig
from respecd.drivers.uvc import UVCConfig
from respecd.errors import ConfigError
from respecd.perception.config import PerceptionConfig
from respecd.profile_overlay import Origin, Resolved, nearest, resolve
from respecd.profile_yaml import KeyPath
from respecd.record.config import RecordingConfig
from respecd.record.live_config import LiveConfig
from respecd.sensors import MAX_RATE_HZ, MIN_RATE_HZ, StrictModel
from respecd.sim.config import SimulationConfig

DEFAULT_PROFILE = "builtin:sim-rover"
DRIVER_TAGS = frozenset(DRIVERS)
NUMBER_ERRORS = frozenset({"float_type", "int_type", "float_parsing", "int_parsing", "int_from_float"})


class SyncConfig(StrictModel):
    max_rate_hz: float = Field(
        MAX_RATE_HZ,
        ge=MIN_RATE_HZ,
        le=MAX_RATE_HZ,
        description="Global cap on the tick rate (the paper's Jetson saturated at 27).",
    )
    min_rate_hz: float = Field(MIN_RATE_HZ, ge=MIN_RATE_HZ, le=MAX_RATE_HZ, description="Floor on the tick rate.")
    window_s: float = Field(1.0, ge=0.25, le=10, description="Window for jitter and stale-ratio statistics (s).")
    tick_phase: float = Field(
        0.5, ge=0, lt=1, description="Tick grid phase, in periods: ticks at (k + phase) / rate on the clock."
    )
    jitter_ms_fair: float = Field(2.0, gt=0, description="Tick jitter (ms) above which health is fair.")
    jitter_ms_poor: float = Field(10.0, gt=0, description="Tick jitter (ms) above which health is poor.")
    stale_fair: float = Field(0.1, ge=0, le=1, description="Stale-frame ratio above which health is fair.")
    stale_poor: float = Field(0.3, ge=0, le=1, description="Stale-frame ratio above which health is poor.")
    frame_queue: int = Field(8, ge=1, le=1024, description="Frames buffered per sensor before the oldest is dropped.")
    bundle_queue: int = Field(
        2, ge=1, le=64, description="Bundles buffered for perception before the oldest is dropped."
    )
    realtime_priority: int = Field(
        10, ge=0, le=49,
        description="The live daemon's event-loop thread (it ticks the synchronizer) in SCHED_FIFO at this "
        "priority, so busy neighbour processes do not keep it off a core, where the process may (LimitRTPRIO= or "
        "CAP_SYS_NICE); threads it starts stay in normal scheduling. 0: normal scheduling.",
    )

    @model_validator(mode="after")
    def _ordered_thresholds(self) -> SyncConfig:
        if self.min_rate_hz > self.max_rate_hz:
            raise ValueError("min_rate_hz must not exceed max_rate_hz")
        if self.jitter_ms_fair > self.jitter_ms_poor or self.stale_fair > self.stale_poor:
            raise ValueError("fair thresholds must not exceed poor thresholds")
        return self


class TelemetryConfig(StrictModel):
    status_period_s: float = Field(1.0, gt=0, le=60, description="Seconds between status lines.")
    power_rails: Literal["auto", "off"] = Field(
        "auto", description="Read Jetson INA3221 power rails from sysfs when present ('off': use the power model)."
    )
    watchdog_stall_s: float = Field(
        5.0,
        gt=0,
        description="Seconds the synchronizer may go without a tick, or perception hold input without output, "
        "before the systemd watchdog is no longer fed; a sensor this long without frames is listed as degraded.",
    )


SensorEntry = Annotated[
    Union[SimConfig, UVCConfig, FlirOneConfig, RealSenseConfig, ReplayConfig, IWR6843Config],
    Field(discriminator="driver"),
]
"""One sensor entry: the driver's own config model, chosen by ``driver:`` (``respecd.drivers.DRIVERS``)."""


class Profile(StrictModel):
    """A whole profile, as validated: every section with its defaults filled in."""

    name: str = Field(description="Profile name, shown in logs and recorded in MCAP metadata.")
    sensors: list[SensorEntry] = Field(min_length=1, description="The robot's sensors.")
    sync: SyncConfig = Field(SyncConfig(), description="Synchronizer.")
    perception: PerceptionConfig = Field(PerceptionConfig(), description="Fusion detector and attribution.")
    controller: ControllerConfig = Field(ControllerConfig(), description="Q-learning controller.")
    recording: RecordingConfig = Field(RecordingConfig(), description="MCAP recording.")
    live: LiveConfig = Field(LiveConfig(), description="The Foxglove live view's guard (--foxglove).")
    telemetry: TelemetryConfig = Field(TelemetryConfig(), description="Status line, power rails, watchdog.")
    simulation: SimulationConfig = Field(SimulationConfig(), description="The simulated world `sim` sensors look at.")

    @model_validator(mode="after")
    def _unique_sensor_names(self) -> Profile:
        names = [s.name for s in self.sensors]
        duplicated = sorted({n for n in names if names.count(n) > 1})
        if duplicated:
            raise ValueError(f"sensor names must be unique, repeated: {', '.join(duplicated)}")
        return self


@dataclass(frozen=True)
class LoadedProfile:
    """A validated profile with where each value came from, for checks that report ``FILE:LINE``.

    ``label`` is the file asked for; with ``extends:`` a value may have been written by a base
    file, and ``where`` names that file."""

    model: Profile
    label: str
    origins: dict[KeyPath, Origin]

    def where(self, *path: Any) -> str:
        """``FILE:LINE`` of the value at ``path`` (or of its closest written parent)."""
        label, line = nearest(self.origins, path, (self.label, 1))
        return f"{label}:{line}"


def load_profile(source: str | Path = DEFAULT_PROFILE) -> Profile:
    """Read, resolve (``extends:``) and validate a profile file or ``builtin:NAME``; raise ConfigError."""
    return read_profile(source).model


def read_profile(source: str | Path = DEFAULT_PROFILE) -> LoadedProfile:
    """``load_profile`` keeping the file label and the key-path -> (file, line) index.

    Scalars are validated strictly, as their YAML type: ``rate_hz: yes`` (a boolean) or
    ``rate_hz: "30"`` (a string) are errors, not 1 and 30.
    """
    resolved = resolve(str(source))
    try:
        as_json = json.dumps(resolved.document, default=str)  # dates and the like are text to a profile
        return LoadedProfile(Profile.model_validate_json(as_json, strict=True), resolved.label, resolved.origins)
    except ValidationError as err:
        problems = [_format_problem(resolved, e) for e in err.errors()]
        raise ConfigError(f"{resolved.label}: {len(problems)} problem(s)", problems) from err


def _format_problem(resolved: Resolved, error: Any) -> str:
    # pydantic inserts the union tag (e.g. 'sim') into the location; drop it for the YAML path
    loc = tuple(p for p in error["loc"] if not (isinstance(p, str) and p in DRIVER_TAGS))
    kind = error["type"]
    if kind in ("union_tag_invalid", "union_tag_not_found"):
        loc = (*loc, "driver")
    label, line = nearest(resolved.origins, loc, (resolved.label, 1))
    path = ".".join(str(p) for p in loc) or "(top level)"
    message = error["msg"]
    if kind == "extra_forbidden":
        message = "unknown key (check the spelling; `respecd schema` lists the valid keys)"
    elif kind == "missing":
        message = "required key is missing"
    elif kind == "union_tag_invalid":
        tag = error.get("ctx", {}).get("tag")
        message = f"unknown driver {tag!r} (expected one of: {', '.join(sorted(DRIVER_TAGS))})"
    elif kind == "union_tag_not_found":
        message = f"required key is missing (expected one of: {', '.join(sorted(DRIVER_TAGS))})"
    elif kind in NUMBER_ERRORS and isinstance(error.get("input"), bool):
        message = f"expected a number, got {error['input']!r} (YAML reads yes/no/on/off/true/false as booleans)"
    elif kind in NUMBER_ERRORS and isinstance(error.get("input"), str):
        message = f"expected a number, got the text {error['input']!r}" + _quoted_number_hint(error["input"])
    elif kind == "bool_type" and not isinstance(error.get("input"), bool):
        message = f"expected true or false, got {error['input']!r}"
    elif "input" in error and kind != "value_error":
        message = f"{message} (got {error['input']!r})"
    return f"{label}:{line}: {path}: {message}"


def _quoted_number_hint(text: str) -> str:
    """Why a number became text: quoted, or a form YAML 1.1 does not read as a number (1e3 needs a
    dot and a signed exponent there: 1.0e+3)."""
    try:
        value = float(text)
    except ValueError:
        return ""
    import yaml

    if not isinstance(yaml.safe_load(text), str):
        return " (write numbers without quotes)"
    if not math.isfinite(value):
        return f" (YAML reads {text} as text, not a number)"
    return (f" (YAML reads {text} as text, not a number: write {value:g}, or an exponent with a dot and a "
            "sign such as 1.0e+3)")


