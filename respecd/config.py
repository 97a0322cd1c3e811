"""The profile: one YAML file describing sensors, synchronizer, perception, controller,
recording and telemetry, validated by pydantic.

Errors come back as ``FILE:LINE: field.path: message (expected ...)``, one per problem,
because a robotics engineer editing YAML on a rover needs the line, not a traceback.
"""

from __future__ import annotations

import functools
import json
import re
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Annotated, Any, Literal, Union

from pydantic import Field, ValidationError, model_validator

from respecd.control.config import ControllerConfig
from respecd.drivers import config_classes
from respecd.errors import ConfigError
from respecd.perception.config import PerceptionConfig
from respecd.profile_yaml import MAX_BYTES, parse
from respecd.record.config import RecordingConfig
from respecd.sensors import MAX_RATE_HZ, MIN_RATE_HZ, StrictModel
from respecd.sim.config import SimulationConfig

BUILTIN_PREFIX = "builtin:"
DEFAULT_PROFILE = "builtin:sim-rover"
BUILTIN_NAME = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]*")  # a file name in the package, no path
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


def _sensor_union() -> Any:
    classes = tuple(config_classes())
    return Annotated[Union[classes], Field(discriminator="driver")]


@functools.cache
def profile_model() -> type[StrictModel]:
    """The Profile model; built lazily because the sensor union comes from the registry."""

    class Profile(StrictModel):
        name: str = Field(description="Profile name, shown in logs and recorded in MCAP metadata.")
        sensors: list[_sensor_union()] = Field(min_length=1, description="The robot's sensors.")  # type: ignore[valid-type]
        sync: SyncConfig = Field(SyncConfig(), description="Synchronizer.")
        perception: PerceptionConfig = Field(PerceptionConfig(), description="Fusion detector and attribution.")
        controller: ControllerConfig = Field(ControllerConfig(), description="Q-learning controller.")
        recording: RecordingConfig = Field(RecordingConfig(), description="MCAP recording.")
        telemetry: TelemetryConfig = Field(TelemetryConfig(), description="Status line, power rails, watchdog.")
        simulation: SimulationConfig = Field(
            SimulationConfig(), description="The simulated world `sim` sensors look at."
        )

        @model_validator(mode="after")
        def _unique_sensor_names(self) -> Profile:
            names = [s.name for s in self.sensors]
            duplicated = sorted({n for n in names if names.count(n) > 1})
            if duplicated:
                raise ValueError(f"sensor names must be unique, repeated: {', '.join(duplicated)}")
            return self

    return Profile


def json_schema() -> dict[str, Any]:
    schema = profile_model().model_json_schema()
    schema["$schema"] = "https://json-schema.org/draft/2020-12/schema"
    schema["title"] = "respecd profile"
    return schema


@dataclass(frozen=True)
class LoadedProfile:
    """A validated profile with where it came from, for checks that report ``FILE:LINE``."""

    model: Any
    label: str
    lines: dict[tuple[Any, ...], int]

    def line(self, *path: Any) -> int:
        return _nearest_line(self.lines, path)


def load_profile(source: str | Path = DEFAULT_PROFILE) -> Any:
    """Read, parse and validate a profile file (or ``builtin:NAME``); raise ConfigError."""
    return read_profile(source).model


def read_profile(source: str | Path = DEFAULT_PROFILE) -> LoadedProfile:
    """``load_profile`` keeping the file label and the key-path -> line index.

    Scalars are validated strictly, as their YAML type: ``rate_hz: yes`` (a boolean) or
    ``rate_hz: "30"`` (a string) are errors, not 1 and 30.
    """
    label, text = _read_source(str(source))
    parsed = parse(label, text)
    if not isinstance(parsed.document, dict):
        raise ConfigError(f"{label}:1: profile must be a mapping of sections (expected keys like name, sensors)")
    try:
        as_json = json.dumps(parsed.document, default=str)  # dates and the like are text to a profile
        return LoadedProfile(profile_model().model_validate_json(as_json, strict=True), label, parsed.lines)
    except ValidationError as err:
        problems = [_format_problem(label, parsed.lines, e) for e in err.errors()]
        raise ConfigError(f"{label}: {len(problems)} problem(s)", problems) from err


def _read_source(source: str) -> tuple[str, str]:
    if source.startswith(BUILTIN_PREFIX):
        name = source[len(BUILTIN_PREFIX) :]
        resource = resources.files("respecd.profiles") / f"{name}.yaml"  # a mapped package (pyproject package-dir)
        if not BUILTIN_NAME.fullmatch(name) or not resource.is_file():
            raise ConfigError(f"{source}: no built-in profile named {name!r}")
        return f"<{source}>", resource.read_text(encoding="utf-8")
    path = Path(source)
    try:
        with path.open("rb") as handle:  # at most one byte past the limit, whatever the file is
            data = handle.read(MAX_BYTES + 1)  # (/dev/zero or a FIFO has no size to check first)
        if len(data) > MAX_BYTES:
            size = path.stat().st_size if path.is_file() else 0
            what = f"is {size} bytes, more than" if size > MAX_BYTES else "gives more bytes than"
            raise ConfigError(
                f"{path}:1: profile {what} the {MAX_BYTES} allowed "
                "(a profile is a few kB: is this the right file?)"
            )
        return str(path), data.decode("utf-8")
    except FileNotFoundError as err:
        raise ConfigError(f"{path}: no such file") from err
    except IsADirectoryError as err:
        raise ConfigError(f"{path}: is a directory, expected a profile (a YAML file)") from err
    except UnicodeDecodeError as err:
        line = err.object[: err.start].count(b"\n") + 1
        raise ConfigError(f"{path}:{line}: not UTF-8 text: byte {err.start} is {err.object[err.start]:#04x} "
                          "(expected a YAML profile: is this the right file?)") from err
    except OSError as err:
        raise ConfigError(f"{path}: cannot read: {err.strerror or err}") from err


def _format_problem(label: str, lines: dict[tuple[Any, ...], int], error: Any) -> str:
    # pydantic inserts the union tag (e.g. 'sim') into the location; drop it for the YAML path
    loc = tuple(p for p in error["loc"] if not (isinstance(p, str) and p in _tags()))
    kind = error["type"]
    if kind in ("union_tag_invalid", "union_tag_not_found"):
        loc = (*loc, "driver")
    line = _nearest_line(lines, loc)
    path = ".".join(str(p) for p in loc) or "(top level)"
    message = error["msg"]
    if kind == "extra_forbidden":
        message = "unknown key (check the spelling; `respecd schema` lists the valid keys)"
    elif kind == "missing":
        message = "required key is missing"
    elif kind == "union_tag_invalid":
        tag = error.get("ctx", {}).get("tag")
        message = f"unknown driver {tag!r} (expected one of: {', '.join(sorted(_tags()))})"
    elif kind == "union_tag_not_found":
        message = f"required key is missing (expected one of: {', '.join(sorted(_tags()))})"
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
    try:
        float(text)
    except ValueError:
        return ""
    return " (write numbers without quotes)"


@functools.cache
def _tags() -> frozenset[str]:
    from respecd.drivers import DRIVERS

    return frozenset(DRIVERS)


def _nearest_line(lines: dict[tuple[Any, ...], int], loc: tuple[Any, ...]) -> int:
    for cut in range(len(loc), -1, -1):
        if loc[:cut] in lines:
            return lines[loc[:cut]]
    return 1
