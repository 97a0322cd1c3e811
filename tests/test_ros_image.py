"""ROS image encodings (through rosbags-image): colour comes out BGR, Bayer is demosaiced,
YUV converted, grey and depth kept exact, rows padded past their pixels are cut."""

from __future__ import annotations

from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from respecd.record.ros_image import image_pixels

RNG = np.random.default_rng(4)
BGR = RNG.integers(0, 255, (6, 8, 3), dtype=np.uint8)


def _msg(encoding: str, pixels: np.ndarray, pad: int = 0, bigendian: bool = False, rows: int | None = None) -> object:
    data = pixels.astype(pixels.dtype.newbyteorder(">" if bigendian else "<")).tobytes()
    height = rows if rows is not None else pixels.shape[0]
    row = len(data) // pixels.shape[0]
    padded = b"".join(data[i * row:(i + 1) * row] + b"\xee" * pad for i in range(pixels.shape[0]))
    return SimpleNamespace(encoding=encoding, height=height, width=pixels.shape[1], step=row + pad,
                           is_bigendian=int(bigendian), data=np.frombuffer(padded, np.uint8))


@pytest.mark.parametrize("pad", [0, 5])
def test_rgb_and_rgba_come_out_bgr_whatever_the_row_padding(pad: int) -> None:
    np.testing.assert_array_equal(image_pixels(_msg("rgb8", BGR[:, :, ::-1], pad)), BGR)
    np.testing.assert_array_equal(image_pixels(_msg("bgr8", BGR, pad)), BGR)
    rgba = cv2.cvtColor(BGR, cv2.COLOR_BGR2RGBA)
    np.testing.assert_array_equal(image_pixels(_msg("rgba8", rgba, pad)), BGR)


def test_grey_and_depth_stay_exact_in_either_byte_order() -> None:
    depth = RNG.integers(0, 65535, (6, 8), dtype=np.uint16)
    for encoding in ("mono16", "16UC1"):
        out = image_pixels(_msg(encoding, depth, pad=4, bigendian=True))
        assert out.dtype == np.uint16 and out.dtype.isnative
        np.testing.assert_array_equal(out, depth)
    metres = RNG.random((6, 8), dtype=np.float32)
    np.testing.assert_array_equal(image_pixels(_msg("32FC1", metres)), metres)


def test_bayer_yuv_and_nv12_are_converted_as_opencv_does() -> None:
    raw = RNG.integers(0, 255, (6, 8), dtype=np.uint8)
    np.testing.assert_array_equal(image_pixels(_msg("bayer_rggb8", raw)), cv2.cvtColor(raw, cv2.COLOR_BayerBG2BGR))
    uyvy = RNG.integers(0, 255, (6, 8, 2), dtype=np.uint8)
    np.testing.assert_array_equal(image_pixels(_msg("uyvy", uyvy)), cv2.cvtColor(uyvy, cv2.COLOR_YUV2BGR_UYVY))
    nv12 = RNG.integers(0, 255, (9, 8), dtype=np.uint8)  # 6 rows of luma, 3 of interleaved chroma
    out = image_pixels(_msg("nv12", nv12, rows=6))
    np.testing.assert_array_equal(out, cv2.cvtColor(nv12, cv2.COLOR_YUV2BGR_NV12))


def test_what_cannot_be_read_is_a_value_error() -> None:
    with pytest.raises(ValueError, match="unsupported image encoding 'jpeg'"):
        image_pixels(_msg("jpeg", BGR))
    short = _msg("bgr8", BGR)
    short.data = short.data[:-10]  # type: ignore[attr-defined]
    with pytest.raises(ValueError, match="expected 6 rows"):
        image_pixels(short)
