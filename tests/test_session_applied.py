"""What a driver learns on its own reaches everyone who follows configurations.

A FLIR One reports its real frame size only with its first frame (the shared Gen-3 capture
is an 80x60 unit, not the 160x120 a One Pro profile assumes); a UVC camera may negotiate
another mode at start; a radar recovers to its last good profile. None of that is an answer
to ``apply``, yet the synchronizer, the controller, the recorder and the status line must
hear it: the session publishes every change of a driver's ``applied``.
"""

from __future__ import annotations

from pathlib import Path

from respecd.clock import MonotonicClock
from respecd.config import load_profile
from respecd.messages import SensorConfig
from respecd.session import Session

PROFILE = """\
name: flir-only
sensors:
  - name: thermal
    driver: flirone
    modality: thermal
    stream: thermal
    sensor: pro
    rate_hz: 9
    resolution: [160, 120]
    recording: {recording}
    loop: true
perception:
  enabled: false
controller:
  enabled: false
"""


async def test_a_frame_size_the_camera_reports_is_published(shared_data: Path, tmp_path: Path) -> None:
    capture = shared_data / "flirone_pro_gen3_usb_moezemara" / "usb_stream_concat.bin"
    path = tmp_path / "flir.yaml"
    path.write_text(PROFILE.format(recording=capture))
    session = Session(load_profile(path), MonotonicClock())
    heard: list[SensorConfig] = []
    session.hooks.config.append(lambda name, applied: heard.append(applied))
    await session.run(duration=1.5)
    # the start configuration, as the profile assumes a One Pro: 160x120 native
    assert heard[0].resolution == (160, 120) and not any("upscaled" in n for n in heard[0].notes)
    # the camera's frames say 80x60, so the 160x120 it now delivers is upscaled, and everyone hears it
    assert any("upscaled from the native" in n for n in heard[-1].notes)
    assert session.pipeline.applied["thermal"] == session.pipeline.drivers["thermal"].applied == heard[-1]
