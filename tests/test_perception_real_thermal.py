"""The real rover's checkpoint keeps a thermal path that works alone on real LWIR (issue 46): with the RGB camera
off, as the daemon feeds a disabled camera (a black frame), it still finds the people on real night pairs, and with
both cameras on it does not bury them under false boxes. LLVIP is evaluation data: builtin:rgbt never trained on it."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from respecd.lab.detector.data import read_voc
from respecd.lab.detector.metrics import iou_matrix
from respecd.perception import checkpoint
from respecd.perception.config import PerceptionConfig
from respecd.perception.detector import FusionDetector, frames_from_arrays

pytestmark = pytest.mark.usefixtures("one_torch_thread")

PAIRS = ("010005", "190001", "190003")  # 10 annotated people


def _found(detections, people: np.ndarray) -> int:
    boxes = np.array([d.box for d in detections], dtype=np.float32).reshape(-1, 4)
    return int((iou_matrix(people, boxes) >= 0.5).any(1).sum()) if len(boxes) else 0


@pytest.mark.slow
def test_the_real_rovers_thermal_path_alone_finds_people_on_real_lwir(shared_data: Path) -> None:
    config = PerceptionConfig(weights="builtin:rgbt", model=checkpoint.spec_of("builtin:rgbt"))
    detector = FusionDetector.load(config)
    root = shared_data / "llvip_pairs"
    people, found, boxes = 0, {"both": 0, "thermal": 0}, {"both": 0, "thermal": 0}
    for pair in PAIRS:
        vis = cv2.resize(cv2.imread(str(root / "visible" / f"{pair}.jpg")), (640, 512), interpolation=cv2.INTER_AREA)
        ir = cv2.resize(cv2.imread(str(root / "infrared" / f"{pair}.jpg"), cv2.IMREAD_GRAYSCALE), (640, 512),
                        interpolation=cv2.INTER_AREA)
        truth = read_voc(root / "Annotations" / f"{pair}.xml", config.model.classes)[0] * 0.5
        people += len(truth)
        for name, rgb in (("both", vis), ("thermal", np.zeros_like(vis))):
            detections = detector.infer(frames_from_arrays(rgb, ir), attribute=False).detections
            found[name] += _found(detections, truth)
            boxes[name] += len(detections)
    assert found["thermal"] >= 0.7 * people, found  # thermal alone: most people, at the daemon's threshold
    assert found["both"] >= 0.7 * people, found
    assert boxes["both"] <= 2.5 * people, boxes  # both cameras on: not a crowd of false boxes
