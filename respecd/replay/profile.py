"""The profile a replay runs with: the recorded (or given) profile, every sensor swapped for
a ``replay`` driver that serves that sensor's logged frames, recording off, the detector on a
device this machine has (``replay.detector``), and — for a lockstep replay — nothing that reads
this machine's state (the CPU probe).

Each replay sensor carries what the robot's own driver offers (``offered``: the driver built
from the profile's entry, before start, as the live daemon builds its action space), so the
controller's action space comes from the profile and never from what one log recorded."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import structlog
from pydantic import ValidationError

from respecd.errors import ConfigError, InputError
from respecd.messages import Frame
from respecd.record.reader import SessionLog
from respecd.replay import detector

if TYPE_CHECKING:
    from respecd.config import Profile

log = structlog.get_logger(__name__)

# DriverConfigBase fields every sensor entry shares; driver-specific keys are left behind
COMMON_KEYS = ("name", "modality", "enabled", "rate_hz", "resolution", "mode", "tolerance_ms", "calibration", "power")


def first_frames(session: SessionLog) -> dict[str, Frame]:
    """The first logged frame of every sensor (its native resolution and start time)."""
    firsts = {}
    for name in session.sensors:
        frame = next(iter(session.frames(name)), None)
        if frame is not None:
            firsts[name] = frame
    return firsts


def logged_rate(session: SessionLog, sensor: str) -> float:
    """The sensor's recorded frame rate, clamped to 1..30 Hz and rounded up to 0.1 Hz."""
    count = session.frame_count(sensor)
    duration = session.duration_s
    rate = (count - 1) / duration if count > 1 and duration > 0 else 30.0
    return min(30.0, max(1.0, math.ceil(rate * 10 - 1e-6) / 10))


def offered_by(entry: dict[str, Any]) -> dict[str, Any] | None:
    """What the profile entry's own driver offers before start (its ``capabilities``), as JSON;
    None when that driver cannot be built here (no ``driver:`` key, as for a ROS bag's topics,
    or a driver this replay cannot load): the replay driver then offers the paper's space."""
    from respecd.drivers import DRIVERS, config_class, driver_class
    from respecd.drivers.replay import Offered

    key = entry.get("driver")
    if not isinstance(key, str) or key not in DRIVERS or key == "replay":
        return None
    try:
        driver = driver_class(key)(config_class(key).model_validate(entry), None)  # type: ignore[arg-type]
        caps = driver.capabilities
    except Exception as err:  # noqa: BLE001 - any driver's refusal: the replay's own space instead, said once
        log.warning("replay.driver_offer_unknown", sensor=entry.get("name"), driver=key, error=str(err))
        return None
    return Offered.of(caps).model_dump(mode="json")


def replay_sensor(entry: dict[str, Any], session: SessionLog, first: Frame) -> dict[str, Any]:
    sensor = {k: entry[k] for k in COMMON_KEYS if k in entry}
    sensor.update(driver="replay", source=entry["name"], max_rate_hz=logged_rate(session, entry["name"]))
    offered = entry.get("offered") if entry.get("driver") == "replay" else offered_by(entry)
    if offered is not None:
        sensor["offered"] = offered
    if first.data.ndim >= 2 and first.modality != "radar":
        sensor["native_resolution"] = [int(first.data.shape[1]), int(first.data.shape[0])]
    if sensor.get("rate_hz", 30.0) > sensor["max_rate_hz"]:
        sensor["rate_hz"] = sensor["max_rate_hz"]
    return sensor


def empty_sensor(entry: dict[str, Any]) -> dict[str, Any]:
    """A profile sensor the log has no frame of: a replay sensor that serves none."""
    sensor = {k: entry[k] for k in COMMON_KEYS if k in entry}
    sensor.update(driver="replay", source=entry["name"], empty=True)
    offered = entry.get("offered") if entry.get("driver") == "replay" else offered_by(entry)
    if offered is not None:
        sensor["offered"] = offered
    return sensor


def replay_profile(base: dict[str, Any], session: SessionLog, firsts: dict[str, Frame], *, seed: int,
                   lockstep: bool, policy: str | None = None) -> Profile:
    """Validated Profile for the replay (ConfigError with one line per problem)."""
    from respecd.config import Profile

    doc = dict(base)
    sensors = []
    for entry in base.get("sensors", []):
        if entry.get("name") in firsts:
            sensors.append(replay_sensor(entry, session, firsts[entry["name"]]))
        else:  # kept, serving nothing: the action space is the profile's, whatever the log holds
            log.warning("replay.sensor_not_in_log", sensor=entry.get("name"), action="serves no frames")
            sensors.append(empty_sensor(entry))
    if not any(entry.get("name") in firsts for entry in base.get("sensors", [])):
        names = ", ".join(sorted(firsts)) or "none"
        raise InputError(f"{session.path}: no profile sensor has frames in the log (the log has: {names})")
    doc["sensors"] = sensors
    doc["recording"] = {**(base.get("recording") or {}), "enabled": False}
    doc["perception"] = detector.place(base.get("perception"))  # a device this machine can use
    controller = dict(base.get("controller") or {})
    controller["seed"] = seed
    if policy is not None:
        controller["policy"] = policy
    if lockstep:
        controller["system_probe"] = False  # CPU share of this machine would make decisions differ
    doc["controller"] = controller
    try:
        return Profile.model_validate(doc)
    except ValidationError as err:
        where = f"{session.path}: replay profile"
        problems = [f"{where}: {'.'.join(map(str, e['loc']))}: {e['msg']}" for e in err.errors()]
        raise ConfigError(f"{session.path}: recorded profile does not validate", problems) from err
