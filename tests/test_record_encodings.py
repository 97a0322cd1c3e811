"""Recording encodings: a lossless log (every camera PNG) replays to the very detections the
raw log (every camera a RawImage) gives; PNG frames decode lazily, JPEG ones move a little."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from respecd.config import load_profile
from respecd.errors import ConfigError
from respecd.lab.bench import recording
from respecd.record import lazy


@pytest.mark.slow
def test_a_lossless_log_replays_to_the_raw_logs_detections(tmp_path: Path) -> None:
    from respecd.perception.checkpoint import resolve

    try:
        resolve("builtin:sim-rover")
    except ConfigError:
        pytest.skip("no built-in detector checkpoint (run `make weights`)")
    profile = recording._profile(load_profile("builtin:sim-rover"), (640, 360))
    result = recording.compare(profile, ["lossless", "jpeg50"], 3.0, 5, tmp_path)["formats"]
    lossless, jpeg = result["lossless"], result["jpeg50"]
    assert lossless["inferences"] >= 3 and lossless["detections"] > 0  # people in view, the detector ran
    assert lossless["compared"] == lossless["identical_inferences"] == lossless["inferences"]
    assert jpeg["compared"] == jpeg["inferences"] and jpeg["identical_inferences"] < jpeg["inferences"]
    assert lossless["mb_per_s"] > jpeg["mb_per_s"]  # lossless RGB costs room: a choice, not a default


@pytest.mark.parametrize(("image", "shape"), [
    (np.zeros((48, 64, 3), np.uint8), (48, 64, 3)),
    (np.zeros((48, 64), np.uint16), (48, 64)),
    (np.zeros((48, 64, 4), np.uint8), (48, 64, 4)),
])
def test_png_size_is_read_from_its_header_as_imdecode_gives_it(image: np.ndarray, shape: tuple[int, ...]) -> None:
    ok, buf = cv2.imencode(".png", image)
    assert ok and lazy.encoded_shape(buf.tobytes()) == shape
    assert cv2.imdecode(buf, cv2.IMREAD_UNCHANGED).shape == shape
    assert lazy.png_shape(b"\x89PNG\r\n\x1a\n") is None and lazy.png_shape(buf.tobytes()[:20]) is None
