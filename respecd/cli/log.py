"""``respecd log info LOG``: a quick look at a session log — channels, duration, message
counts, sensors and the profile it ran with — without replaying it. ``respecd log export
LOG --to rosbag2 OUT``: the session as a ROS 2 bag.

Every record is read and every chunk's CRC checked, so the counts are what a replay can
really read; damaged stretches are listed by byte range and the exit status is 1."""

from __future__ import annotations

import argparse
import json
import os
import sys
from datetime import datetime, timezone
from typing import Any

from respecd.errors import InputError


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="log_command", metavar="ACTION")
    info = sub.add_parser("info", help="channels, duration, message counts, sensors, profile")
    info.add_argument("log", metavar="LOG", help="an MCAP session log (respecd --record) or a ROS bag")
    info.add_argument("--json", action="store_true", help="print the description as JSON")
    info.add_argument("--profile", action="store_true", help="also print the recorded profile (JSON)")
    export = sub.add_parser("export", help="convert a session log: --to rosbag2 OUT_DIR (MCAP storage, cdr)")
    export.add_argument("log", metavar="LOG", help="an MCAP session log (respecd --record)")
    export.add_argument("--to", choices=("rosbag2",), required=True, help="output format")
    export.add_argument("out", metavar="OUT_DIR", help="the bag directory to create (must not exist)")


def main(args: argparse.Namespace) -> int:
    command = getattr(args, "log_command", None)
    if command not in ("info", "export"):
        raise InputError("log: expected an action: `respecd log info LOG` or `respecd log export LOG --to rosbag2 DIR`")
    from respecd.record.reader import open_log
    from respecd.record.rosbag_in import is_bag

    if command == "export":
        return export(args)
    if is_bag(args.log):
        description = describe_bag(args.log)
        _print(json.dumps(description, indent=2) if args.json else render_bag(description))
        for note in description["metadata_mismatch"]:
            print(f"respecd: warning: {args.log}: metadata.yaml: {note}; the storage's numbers are shown",
                  file=sys.stderr)
        return 0
    session = open_log(args.log, verify=True, warn=False)
    description = describe(session)
    text = json.dumps(description, indent=2) if args.json else render(description)
    if args.profile and not args.json:
        text += "\n" + json.dumps(_profile(session), indent=2)
    _print(text)
    for damage in session.damage:
        print(f"respecd: {session.path}: DAMAGED {damage.describe()}", file=sys.stderr)
    return 1 if session.damage else 0


def _print(text: str) -> None:
    try:
        print(text, flush=True)
    except BrokenPipeError:  # `respecd log info LOG | head`: the reader left, that is fine
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())


def _profile(session: Any) -> dict[str, Any] | None:
    """The recorded profile; a damaged one is listed as damage, not raised."""
    try:
        return session.profile_dict()
    except InputError as err:
        from respecd.record.walk import Damage

        session.note_damage(Damage(0, 0, f"recorded profile metadata: {err}"))
        return None


def describe_bag(path: str) -> dict[str, Any]:
    """A robot's bag: its topics, and the sensors ``--replay`` would take from them."""
    from respecd.record.rosbag_in import open_bag

    bag = open_bag(path, None, warn=False)
    duration = bag.duration_s
    return {
        "file": str(bag.path),
        "bytes": bag.size,
        "kind": "ROS 1 bag" if bag.path.suffix == ".bag" else "rosbag2",
        "start_utc": _utc(bag.start_ns),
        "duration_s": round(duration, 3),
        "messages": bag.message_count,
        "topics": [{"topic": c.topic, "type": c.schema, "messages": c.count, "rate_hz": _rate(c.count, duration)}
                   for c in sorted(bag.channels.values(), key=lambda c: c.topic)],
        "guessed_topics": bag.topic_map,
        "metadata_mismatch": bag.metadata_notes,  # metadata.yaml's numbers the storage disproved
    }


def render_bag(d: dict[str, Any]) -> str:
    guess = ",".join(f"{k}={v}" for k, v in d["guessed_topics"].items())
    lines = [
        f"file:      {d['file']} ({d['bytes'] / 2**20:.1f} MiB)   {d['kind']}",
        f"start:     {d['start_utc'] or '-'}",
        f"duration:  {d['duration_s']:.2f} s",
        f"messages:  {d['messages']} in {len(d['topics'])} topics",
        f"replay:    respecd --replay {d['file']} --topics {guess}" if guess else "replay:    no sensor topics",
        "topics:",
    ]
    for t in d["topics"]:
        lines.append(f"  {t['topic']:<30} {t['type']:<34} {t['messages']:>7} msgs {t['rate_hz'] or 0:>6.1f} Hz")
    return "\n".join(lines)


def export(args: argparse.Namespace) -> int:
    from pathlib import Path

    from respecd.outputs import check_output_dir
    from respecd.record.reader import open_log
    from respecd.record.rosbag_out import export_rosbag2

    check_output_dir("OUT_DIR", args.out, must_be_new=True)  # the bag Writer makes it and its parents
    session = open_log(args.log)
    counts = export_rosbag2(session, Path(args.out))
    print(f"{args.out}: rosbag2 (mcap, cdr), {sum(counts.values())} messages on {len(counts)} topics")
    return 0


def describe(session: Any) -> dict[str, Any]:
    """Plain fields of a ``SessionLog`` (what ``--json`` prints)."""
    duration = session.duration_s
    profile = _profile(session)
    meta = session.metadata.get("respecd.session", {})
    channels = [
        {
            "topic": c.topic,
            "schema": c.schema,
            "messages": c.count,
            "rate_hz": _rate(c.count, duration),
        }
        for c in sorted(session.channels.values(), key=lambda c: c.topic)
    ]
    sensors = {}
    for name, modality in sorted(session.sensors.items()):
        channel = session.channels[f"/sensors/{name}"]
        sensors[name] = {
            "modality": modality,
            "frames": channel.count,
            "rate_hz": _rate(channel.count, duration),
            "encoding": channel.schema,
            "raw_channel": f"/sensors/{name}/raw" in session.channels,
        }
    return {
        "file": str(session.path),
        "bytes": session.size,
        "truncated": session.truncated,
        "start_utc": _utc(session.start_ns),
        "duration_s": round(duration, 3),
        "messages": session.message_count,
        "channels": channels,
        "sensors": sensors,
        "profile": profile.get("name") if profile else None,
        "segment": meta.get("segment"),
        "respecd_version": meta.get("respecd_version"),
        "format": int(meta.get("format", "1")),  # 1: respecd 0.1.0's JSON/base64 messages
        "ground_truth": _has_ground_truth(session),
        "damaged": bool(session.damage),
        "damage": [{"start": d.start, "end": d.end, "reason": d.reason} for d in session.damage],
    }


def _rate(count: int, duration: float) -> float | None:
    """Messages per second: intervals over the span between the first and last message."""
    return round((count - 1) / duration, 2) if duration > 0 and count > 1 else None


def _utc(ns: int) -> str | None:
    if ns <= 0:
        return None
    return datetime.fromtimestamp(ns / 1e9, tz=timezone.utc).isoformat(timespec="milliseconds")


def _has_ground_truth(session: Any) -> bool:
    """True when the first RGB frame carries ``meta["gt"]`` (simulated sessions do)."""
    rgb = [n for n, m in session.sensors.items() if m == "rgb"]
    if not rgb:
        return False
    for frame in session.frames(rgb[0]):
        return "gt" in frame.meta
    return False


def render(d: dict[str, Any]) -> str:
    cut = "  TRUNCATED: no summary; readable up to the last complete chunk" if d["truncated"] else ""
    if d["damaged"]:
        cut += f"  DAMAGED: {len(d['damage'])} stretch(es) skipped; counts are what can be read"
    lines = [
        f"file:      {d['file']} ({d['bytes'] / 2**20:.1f} MiB){cut}",
        f"profile:   {d['profile'] or '(not recorded)'}   respecd {d['respecd_version'] or '?'}   format {d['format']}"
        + (f"   segment {d['segment']}" if d["segment"] not in (None, "0") else ""),
        f"start:     {d['start_utc'] or '-'}",
        f"duration:  {d['duration_s']:.2f} s",
        f"messages:  {d['messages']} in {len(d['channels'])} channels"
        + ("   ground truth: yes" if d["ground_truth"] else ""),
        "sensors:",
    ]
    for name, s in d["sensors"].items():
        raw = " + raw bytes" if s["raw_channel"] else ""
        lines.append(f"  {name:<12} {s['modality']:<8} {s['frames']:>7} frames {s['rate_hz'] or 0:>6.1f} Hz  "
                     f"{s['encoding']}{raw}")
    lines.append("channels:")
    for c in d["channels"]:
        lines.append(f"  {c['topic']:<28} {c['schema']:<26} {c['messages']:>7} msgs {c['rate_hz'] or 0:>6.1f} Hz")
    return "\n".join(lines)
