"""Darknet importer: same outputs as OpenCV's own Darknet reader on a real image, clear errors.

OpenCV's ``cv2.dnn.readNetFromDarknet`` is an independent implementation of the cfg and
.weights formats (OpenCV 4.x; 5.0 dropped it, so the test extra pins 4.14).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from respecd.errors import InputError
from respecd.perception import darknet

pytestmark = pytest.mark.usefixtures("one_torch_thread")

MODELS = ("yolo-fastest-1.1_body", "yolo-fastest-1.1-xl")


@pytest.fixture
def zoo(shared_data: Path) -> Path:
    return shared_data.parent / "pretrained" / "yolo_fastest"


def _opencv(cfg: Path, weights: Path, blob: np.ndarray) -> tuple[list[np.ndarray], list[np.ndarray]]:
    if not hasattr(cv2.dnn, "readNetFromDarknet"):
        pytest.fail(f"OpenCV {cv2.__version__} has no Darknet reader: install the test extra (opencv <5)")
    net = cv2.dnn.readNetFromDarknet(str(cfg), str(weights))
    net.setInput(blob)
    yolo = net.forward(list(net.getUnconnectedOutLayersNames()))
    net.setInput(blob)
    raw = net.forward(["conv_120", "conv_129"])  # the convolutions feeding the two [yolo] layers
    return list(yolo), list(raw)


@pytest.mark.parametrize("name", MODELS)
def test_matches_opencv_on_a_real_image(zoo: Path, shared_data: Path, name: str) -> None:
    image = cv2.imread(str(shared_data / "llvip_pairs" / "visible" / "190001.jpg"))
    blob = cv2.dnn.blobFromImage(image, 1 / 255.0, (416, 320), swapRB=True, crop=False)  # (1, 3, 320, 416)
    ref_yolo, ref_raw = _opencv(zoo / f"{name}.cfg", zoo / f"{name}.weights", blob)
    net = darknet.load(zoo / f"{name}.cfg", zoo / f"{name}.weights")
    with torch.inference_mode():
        raw = net(torch.from_numpy(blob))
    for ours, ref in zip(raw, ref_raw, strict=True):
        assert ours.shape == ref.shape
        assert np.abs(ours.numpy() - ref).max() < 1e-4 * max(1.0, np.abs(ref).max())  # eps 1e-5 fails
    for out, spec, ref in zip(raw, net.yolo_specs, ref_yolo, strict=True):
        rows = darknet.decode_yolo(out, spec, (320, 416))[0].numpy()  # (N, 5 + nc)
        rows[:, [0, 2]] /= 416
        rows[:, [1, 3]] /= 320  # OpenCV's rows are normalised to the input
        assert rows.shape == ref.shape
        np.testing.assert_allclose(rows[:, :5], ref[:, :5], atol=2e-4)
        kept = ref[:, 5:] > 0  # OpenCV zeroes class scores below its threshold and folds objectness in
        np.testing.assert_allclose((rows[:, 4:5] * rows[:, 5:])[kept], ref[:, 5:][kept], atol=2e-4)
    assert max(r[:, 4].max() for r in ref_yolo) > 0.3  # the image has people: the comparison covers real detections


def test_weights_of_the_wrong_size_name_the_offset(zoo: Path, tmp_path: Path) -> None:
    data = (zoo / "yolo-fastest-1.1_body.weights").read_bytes()
    short = tmp_path / "short.weights"
    short.write_bytes(data[:-400])
    expected = r"ends at byte 1177204 while reading the kernel of layer 129 \(convolutional, 18 filters\)"
    with pytest.raises(InputError, match=expected):
        darknet.load(zoo / "yolo-fastest-1.1_body.cfg", short)
    with pytest.raises(InputError, match=r"left over"):
        darknet.load(zoo / "yolo-fastest-1.1_body.cfg", zoo / "yolo-fastest-1.1-xl.weights")


def test_cfg_errors_name_file_and_line(tmp_path: Path) -> None:
    cfg = tmp_path / "bad.cfg"
    cfg.write_text("[net]\nwidth=64\n\n[convolutional]\nfilters=8\nsize=3\n\n[lstm]\n", encoding="utf-8")
    with pytest.raises(InputError, match=r"bad.cfg:8: unsupported Darknet layer \[lstm\]"):
        darknet.load(cfg)
    cfg.write_text("[net]\n[convolutional]\nfilters=eight\n", encoding="utf-8")
    with pytest.raises(InputError, match=r"bad.cfg:2: \[convolutional\] filters='eight': expected a number"):
        darknet.load(cfg)
    cfg.write_text("[net]\n[convolutional]\nfilters=8\n[shortcut]\nfrom=-5\n", encoding="utf-8")
    with pytest.raises(InputError, match=r"bad.cfg:4: \[shortcut\] refers to layer -5"):
        darknet.load(cfg)
