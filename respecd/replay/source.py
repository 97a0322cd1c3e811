"""What a replay reads: the log (a respecd MCAP log, or a robot's ROS bag through a topic map)
and the profile it replays with (given, or the one recorded in the log)."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

from respecd.errors import InputError
from respecd.record.reader import open_log


def open_source(path: str | Path, topics: str | None) -> Any:
    """A respecd log, or a robot's ROS bag read through the topic map (guessed, and the
    guess printed, when ``topics`` is absent)."""
    from respecd.record.rosbag_in import is_bag, open_bag, parse_topics

    if not is_bag(path):
        if topics:
            raise InputError(f"--topics: applies to ROS bags only; {path} is a respecd log (its sensors are named)")
        return open_log(path)
    bag = open_bag(path, parse_topics(topics))
    if not bag.topic_map:
        raise InputError(f"{path}: no sensor_msgs Image/CompressedImage/PointCloud2/Imu topic to replay "
                         f"(topics: {', '.join(f'{t} [{c.schema}]' for t, c in sorted(bag.channels.items()))})")
    for note in bag.metadata_notes:
        print(f"respecd: warning: {path}: metadata.yaml: {note}; replaying what the storage holds", file=sys.stderr)
    if not topics:
        guess = ",".join(f"{k}={v}" for k, v in bag.topic_map.items())
        print(f"respecd: --topics not given; guessed from message types: --topics {guess}", file=sys.stderr)
    return bag


def base_profile(config: str | Path | dict[str, Any] | None, session: Any) -> dict[str, Any]:
    """``config`` when given explicitly (a file, or a profile already loaded as a dict), else the
    profile recorded in the log (for a ROS bag: the default profile's perception and controller
    with one sensor per mapped topic)."""
    from respecd.config import DEFAULT_PROFILE, load_profile

    explicit = config is not None and not (isinstance(config, (str, Path)) and str(config) in ("", DEFAULT_PROFILE))
    if getattr(session, "topic_map", None) is not None:
        source = _load(config) if explicit else dict(load_profile(DEFAULT_PROFILE).model_dump(mode="json"))
        named = {s["name"]: s for s in source.get("sensors", [])} if explicit else {}
        source["sensors"] = [named.get(name, {"name": name, "modality": name}) for name in session.topic_map]
        return source
    if explicit:
        return _load(config)
    recorded = session.profile_dict()
    if recorded is None:
        damage = getattr(session, "damage", None)
        why = f"the log's recorded profile was lost to damage ({damage[0].describe()})" if damage else \
            "the log has no recorded profile"
        raise InputError(f"{session.path}: {why}; pass the one it ran with: --config FILE")
    return dict(recorded)


def _load(config: Any) -> dict[str, Any]:
    from respecd.config import load_profile

    if isinstance(config, dict):
        return dict(config)
    return dict(load_profile(config).model_dump(mode="json"))
