"""The profile: one YAML file describing sensors, synchronizer, perception, controller,
recording and telemetry, validated by pydantic.

Errors come back as ``FILE:LINE: field.path: message (expected ...)``, one per problem,
because a robotics engineer editing YAML on a rover needs the line, not a traceback.
"""

from __future__ import annotations

import functools
from importlib import resources
from pathlib import Path
from typing import Annotated, Any, Literal, Union

import yaml
from pydantic import Field, ValidationError, model_validator

from respecd.control.config import ControllerConfig
from respecd.drivers import config_classes
from respecd.errors import ConfigError
from respecd.perception.config import PerceptionConfig
from respecd.record.config import RecordingConfig
from respecd.sensors import MAX_RATE_HZ, MIN_RATE_HZ, StrictModel
from respecd.sim.config import SimulationConfig

BUILTIN_PREFIX = "builtin:"
DEFAULT_PROFILE = "builtin:sim-rover"


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
        5.0, gt=0, description="Seconds without bundles after which the systemd watchdog is no longer fed."
    )


def _sensor_union() -> Any:
    classes = tuple(config_classes())
    return Annotated[Union[classes], Field(discriminator="driver")]  # type: ignore[valid-type]


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


def load_profile(source: str | Path = DEFAULT_PROFILE) -> Any:
    """Read, parse and validate a profile file (or ``builtin:NAME``); raise ConfigError."""
    label, text = _read_source(str(source))
    try:
        document = yaml.safe_load(text)
    except yaml.YAMLError as err:
        mark = getattr(err, "problem_mark", None)
        line = mark.line + 1 if mark is not None else 0
        problem = getattr(err, "problem", None) or str(err)
        raise ConfigError(f"{label}:{line}: not valid YAML: {problem}") from err
    if not isinstance(document, dict):
        raise ConfigError(f"{label}:1: profile must be a mapping of sections (expected keys like name, sensors)")
    try:
        return profile_model().model_validate(document)
    except ValidationError as err:
        lines = _line_index(text)
        problems = [_format_problem(label, lines, e) for e in err.errors()]
        raise ConfigError(f"{label}: {len(problems)} problem(s)", problems) from err


def _read_source(source: str) -> tuple[str, str]:
    if source.startswith(BUILTIN_PREFIX):
        name = source[len(BUILTIN_PREFIX) :]
        resource = resources.files("respecd.profiles") / f"{name}.yaml"  # a mapped package (pyproject package-dir)
        if not resource.is_file():
            raise ConfigError(f"{source}: no built-in profile named {name!r}")
        return f"<{source}>", resource.read_text(encoding="utf-8")
    path = Path(source)
    try:
        return str(path), path.read_text(encoding="utf-8")
    except FileNotFoundError as err:
        raise ConfigError(f"{path}: no such file") from err
    except (OSError, UnicodeDecodeError) as err:
        raise ConfigError(f"{path}: cannot read: {err}") from err


def _line_index(text: str) -> dict[tuple[Any, ...], int]:
    """Map each key path in the YAML document to its 1-based line number."""
    index: dict[tuple[Any, ...], int] = {}
    try:
        root = yaml.compose(text, Loader=yaml.SafeLoader)
    except yaml.YAMLError:
        return index

    def walk(node: yaml.Node, path: tuple[Any, ...]) -> None:
        index[path] = node.start_mark.line + 1
        if isinstance(node, yaml.MappingNode):
            for key_node, value_node in node.value:
                child = (*path, key_node.value)
                walk(value_node, child)
                index[child] = key_node.start_mark.line + 1
        elif isinstance(node, yaml.SequenceNode):
            for i, item in enumerate(node.value):
                walk(item, (*path, i))

    if root is not None:
        walk(root, ())
    return index


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
    elif "input" in error and kind != "value_error":
        message = f"{message} (got {error['input']!r})"
    return f"{label}:{line}: {path}: {message}"


@functools.cache
def _tags() -> frozenset[str]:
    from respecd.drivers import DRIVERS

    return frozenset(DRIVERS)


def _nearest_line(lines: dict[tuple[Any, ...], int], loc: tuple[Any, ...]) -> int:
    for cut in range(len(loc), -1, -1):
        if loc[:cut] in lines:
            return lines[loc[:cut]]
    return 1
