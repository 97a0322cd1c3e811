"""``record_simulated``: a lockstep recording is the same log however busy the machine is, and
every frame the session rendered is in it (a live recording's frame count follows the load)."""

from __future__ import annotations

from pathlib import Path

from mcap.reader import make_reader

from respecd.config import load_profile
from respecd.record.simulated import record_simulated


def _messages(log: Path) -> list[tuple[str, int]]:
    """(topic, log time since the first message in ns) of every message, in log order."""
    with open(log, "rb") as f:
        found = [(channel.topic, message.log_time) for _, channel, message in make_reader(f).iter_messages()]
    start = min(t for _, t in found)
    return [(topic, t - start) for topic, t in found]


def test_a_lockstep_recording_repeats_itself_with_every_frame(tmp_path: Path) -> None:
    base = load_profile("builtin:sim-rover")
    sensors = [s.model_copy(update={"resolution": (640, 360)}) if s.modality == "rgb" else s
               for s in base.sensors if s.modality != "depth"]
    profile = base.model_copy(update={"sensors": sensors})
    a = record_simulated(profile, tmp_path / "a.mcap", seconds=2.0, seed=1)
    b = record_simulated(profile, tmp_path / "b.mcap", seconds=2.0, seed=1)
    assert a == tmp_path / "a.mcap" and sorted(p.name for p in tmp_path.iterdir()) == ["a.mcap", "b.mcap"]
    first, second = _messages(a), _messages(b)
    assert first == second  # same messages at the same session times, whatever the load did between them
    rgb = [t for topic, t in first if topic == "/sensors/rgb"]
    assert len(rgb) >= 15 and max(rgb) > 1.8e9  # 2 s at 10 Hz or more, to the session's end
    assert {"/sensors/thermal", "/sensors/radar", "/respecd/decision"} <= {topic for topic, _ in first}
