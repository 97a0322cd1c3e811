"""``sensor_msgs/Image`` pixels by their ROS encoding, through ``rosbags-image``.

rosbags-image holds the encoding table and the colour conversions (RGB/BGR with or without
alpha, 8 and 16 bit, Bayer patterns, YUV 4:2:2 and NV12/NV21, the generic ``8UC3``...
forms) the way cv_bridge reads them. It reads a message's buffer as tightly packed rows,
so rows padded to a larger ``step`` are cut to their pixels here first (a camera driver
may align rows; ROS allows it).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from rosbags.image import ImageError, image_to_cvimage
from rosbags.image.image import Format, to_cvtype

_GREY = (Format.GRAY, Format.GENERIC)
_PLANAR_420 = (Format.YUV_NV12, Format.YUV_NV21)  # a luma plane of h rows, then h/2 rows of chroma


@dataclass(frozen=True)
class _Packed:
    """The fields of a ``sensor_msgs/Image`` rosbags-image reads, rows without padding."""

    encoding: str
    height: int
    width: int
    is_bigendian: int
    data: np.ndarray


def image_pixels(msg: Any) -> np.ndarray:
    """The pixels of ``msg``: colour as BGR (8-bit colour stays 8-bit), grey and generic
    encodings (mono16, 16UC1, 32FC1 ...) as they are. ValueError for what cannot be read."""
    encoding, height, width, step = str(msg.encoding), int(msg.height), int(msg.width), int(msg.step)
    try:
        bits, fmt, typestr, channels = to_cvtype(encoding)
    except ImageError as err:
        raise ValueError(f"unsupported image encoding {encoding!r}") from err
    rows = height * 3 // 2 if fmt in _PLANAR_420 else height
    row_bytes = width * channels * np.dtype(typestr).itemsize
    raw = np.asarray(msg.data, dtype=np.uint8)
    if step < row_bytes or raw.size < rows * step:
        raise ValueError(f"{encoding} image {width}x{height}: {raw.size} bytes with step {step}, expected "
                         f"{rows} rows of at least {row_bytes} bytes")
    packed = np.ascontiguousarray(raw[: rows * step].reshape(rows, step)[:, :row_bytes])
    image = _Packed(encoding, rows, width, int(msg.is_bigendian), packed)
    try:
        pixels = image_to_cvimage(image, None if fmt in _GREY else "bgr8" if bits == 8 else "bgr16")  # type: ignore[arg-type]
    except ImageError as err:
        raise ValueError(f"cannot convert a {encoding} image: {err}") from err
    return np.array(pixels)  # its own, writable, native byte order
