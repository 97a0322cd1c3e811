"""Camera pairs from recorded sessions: what ``respecd adapt`` learns from.

A session log (``respecd --record``) holds every sensor's frames and the profile the session
ran with, calibration included. ``open_recording`` checks that a log can be learned from:
a respecd log (not a ROS bag), an RGB and a thermal camera that both recorded frames, and
both calibrated (intrinsics; the thermal camera's pose relative to the RGB camera), since
the RGB camera's boxes are carried into the thermal view through that calibration. Every
problem is an ``InputError`` naming the log and what it lacks (exit 2).

``paired_frames`` streams, every ``every_s`` seconds of RGB time, the RGB frame with the
nearest frame of each aux sensor within ``max_skew_s`` (thermal is required; a thermal
flat-field frame never pairs), in one pass over the log. Frames come from the log reader,
so raw, PNG and JPEG camera channels alike; JPEG frames between the chosen ones are never
decoded.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pydantic import ValidationError

from respecd.errors import InputError
from respecd.messages import Frame
from respecd.record.reader import Demux, SessionLog, open_log
from respecd.record.topics import meta_topic, raw_topic, sensor_topic
from respecd.sensors import Calibration

CAMERAS = ("rgb", "thermal")
RECORD_HINT = "record sessions with `respecd --record LOG`"


@dataclass
class Recording:
    """A log that can be learned from: its sensors by modality and their calibration."""

    path: Path
    session: SessionLog
    sensors: dict[str, str]  # modality -> the sensor recording it (the first of each)
    calibration: dict[str, Calibration | None]  # per modality, as calibration_from_profile gives it
    perception: dict[str, Any]  # the recorded profile's perception section (thermal scaling and the like)

    @property
    def truncated(self) -> bool:
        return self.session.truncated


def open_recording(path: str | Path, profile: dict[str, Any] | None = None) -> Recording:
    """Check ``path`` and read its sensors and calibration; ``profile`` replaces the recorded one."""
    from respecd.record.rosbag_in import is_bag

    p = Path(path)
    if is_bag(p):
        raise InputError(f"{p}: a ROS bag, not a respecd session log: it records no camera calibration "
                         f"for adapt to map boxes between the cameras with; {RECORD_HINT}")
    session = open_log(p, warn=False)
    sensors: dict[str, str] = {}
    for name, modality in session.sensors.items():
        if session.frame_count(name) > 0:
            sensors.setdefault(modality, name)
    missing = [m for m in CAMERAS if m not in sensors]
    if missing:
        found = ", ".join(f"{n} ({m})" for n, m in sorted(session.sensors.items())) or "none"
        raise InputError(f"{p}: no {' and no '.join(missing)} camera frames in this log (sensors: {found}); "
                         "adapt learns thermal from the RGB camera, so it needs both in the same session")
    if profile is None:
        profile = session.profile_dict()
        if profile is None:
            raise InputError(f"{p}: no recorded profile, so no camera calibration (not written by respecd?); "
                             "pass the profile it ran with: --config FILE")
    calibration = _calibration(p, profile, sensors)
    perception = profile.get("perception") if isinstance(profile.get("perception"), dict) else {}
    return Recording(p, session, sensors, calibration, dict(perception or {}))


def _calibration(path: Path, profile: dict[str, Any], sensors: dict[str, str]) -> dict[str, Calibration | None]:
    """Per modality the recording sensor's calibration; both cameras need intrinsics."""
    entries = {s.get("name"): s for s in profile.get("sensors") or [] if isinstance(s, dict)}
    out: dict[str, Calibration | None] = {}
    for modality, name in sensors.items():
        raw = (entries.get(name) or {}).get("calibration")
        try:
            out[modality] = Calibration.model_validate(raw) if raw is not None else None
        except ValidationError as err:
            first = err.errors()[0]
            where = ".".join(str(part) for part in first["loc"])
            raise InputError(f"{path}: sensor {name!r}: calibration.{where}: {first['msg']}") from err
    for modality in CAMERAS:
        cal = out.get(modality)
        if cal is None or cal.intrinsics is None:
            raise InputError(f"{path}: sensor {sensors[modality]!r} ({modality}) has no calibration.intrinsics in "
                             "the recorded profile: adapt maps the RGB camera's boxes into the thermal view with the "
                             "cameras' calibration; pass a profile that has it: --config FILE")
    return out


class Nearest:
    """The frame nearest a time, from a time-ordered stream read forward only."""

    def __init__(self, frames: Iterator[Frame]) -> None:
        self.frames = (f for f in frames if not f.meta.get("ffc"))  # a flat-field frame shows the shutter
        self.before: Frame | None = None
        self.after: Frame | None = next(self.frames, None)

    def at(self, t: float, max_skew_s: float) -> Frame | None:
        while self.after is not None and self.after.t <= t:
            self.before, self.after = self.after, next(self.frames, None)
        near = min((f for f in (self.before, self.after) if f is not None), key=lambda f: abs(f.t - t), default=None)
        return near if near is not None and abs(near.t - t) <= max_skew_s else None


def paired_frames(recording: Recording, aux: tuple[str, ...], every_s: float,
                  max_skew_s: float) -> Iterator[dict[str, Frame]]:
    """Every ``every_s`` s of RGB time: {"rgb": frame, aux modality: the nearest frame, ...}, thermal always."""
    wanted = ["rgb", *(m for m in aux if m in recording.sensors)]
    if "thermal" not in wanted:
        wanted.append("thermal")
    names = {m: recording.sensors[m] for m in wanted}
    owner = {topic(n): n for n in names.values() for topic in (sensor_topic, raw_topic, meta_topic)}
    session = recording.session
    demux = Demux(session.messages(list(owner)), owner)  # one pass over the log for all of them
    nearest = {m: Nearest(session.frames(n, demux, lazy=True)) for m, n in names.items() if m != "rgb"}
    due = -math.inf
    for rgb in session.frames(names["rgb"], demux, lazy=True):
        if rgb.t < due:
            continue
        frames = {"rgb": rgb}
        for modality, stream in nearest.items():
            frame = stream.at(rgb.t, max_skew_s)
            if frame is not None:
                frames[modality] = frame
        if "thermal" in frames:
            due = rgb.t + every_s
            yield frames
