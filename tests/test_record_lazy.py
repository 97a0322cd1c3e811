"""Logged JPEG frames decoded on first use: the size without decoding, one decode, deferred resizes."""

from __future__ import annotations

import dataclasses
import threading

import cv2
import numpy as np
import pytest

from respecd.messages import Frame
from respecd.record.lazy import LazyFrame, derive, jpeg_shape
from respecd.replay.counterfactual import resize


def _jpeg(image: np.ndarray, **params: int) -> bytes:
    flags = [p for kv in params.items() for p in (getattr(cv2, kv[0]), kv[1])]
    ok, buf = cv2.imencode(".jpg", image, flags)
    assert ok
    return buf.tobytes()


@pytest.mark.parametrize("shape", [(360, 640, 3), (120, 160), (7, 9, 3)])
@pytest.mark.parametrize("progressive", [0, 1])
def test_jpeg_shape_is_what_imdecode_gives(shape: tuple[int, ...], progressive: int) -> None:
    image = np.random.default_rng(0).integers(0, 255, shape, dtype=np.uint8)
    data = _jpeg(image, IMWRITE_JPEG_QUALITY=90, IMWRITE_JPEG_PROGRESSIVE=progressive)
    decoded = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    assert jpeg_shape(data) == decoded.shape


def test_jpeg_shape_refuses_what_is_not_a_jpeg() -> None:
    ok, png = cv2.imencode(".png", np.zeros((4, 4, 3), np.uint8))
    assert jpeg_shape(png.tobytes()) is None
    assert jpeg_shape(b"\xff\xd8\xff") is None  # cut before any marker
    assert jpeg_shape(b"") is None


def _lazy(image: np.ndarray, calls: list[str]) -> LazyFrame:
    def decode() -> np.ndarray:
        calls.append(threading.current_thread().name)
        return image.copy()

    return LazyFrame("rgb", 1.5, 7, meta={"gt": [[0, 0, 8, 4]]}, decode=decode, shape=image.shape)


def test_a_lazy_frame_decodes_once_when_its_pixels_are_first_read() -> None:
    image = np.arange(4 * 6 * 3, dtype=np.uint8).reshape(4, 6, 3)
    calls: list[str] = []
    frame = _lazy(image, calls)
    assert isinstance(frame, Frame) and frame.shape == (4, 6, 3) and not frame.decoded
    assert (frame.t, frame.seq, frame.modality) == (1.5, 7, "rgb")
    assert calls == []
    assert np.array_equal(frame.data, image) and frame.data is frame.data
    assert calls == ["MainThread"] and frame.decoded
    with pytest.raises(dataclasses.FrozenInstanceError):
        frame.t = 2.0  # type: ignore[misc]
    assert np.array_equal(dataclasses.replace(frame, seq=8).data, image)


def test_threads_reading_at_once_share_one_decode() -> None:
    calls: list[str] = []
    frame = _lazy(np.zeros((4, 6, 3), np.uint8), calls)
    threads = [threading.Thread(target=lambda: frame.data) for _ in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(calls) == 1


def test_a_resize_waits_for_the_pixels_and_equals_the_eager_one() -> None:
    image = np.random.default_rng(1).integers(0, 255, (36, 64, 3), dtype=np.uint8)
    calls: list[str] = []
    eager = Frame("rgb", 1.5, 7, image, {"gt": [[0, 0, 8, 4]]})
    for target, upscale in (((32, 18), False), ((128, 72), True)):
        lazy = resize(_lazy(image, calls), target)
        assert isinstance(lazy, LazyFrame) and lazy.shape == (target[1], target[0], 3) and calls == []
        reference = resize(eager, target)
        assert np.array_equal(lazy.data, reference.data) and lazy.meta == reference.meta
        assert lazy.meta["gt"] != eager.meta["gt"]
        assert (lazy.upscale_of is not None) == upscale
        calls.clear()


def test_an_upscale_of_an_upscale_names_the_logged_frame() -> None:
    logged = Frame("thermal", 0.0, 0, np.zeros((120, 160), np.uint16))
    once = derive(logged, lambda d: cv2.resize(d, (320, 240)), (240, 320), {}, upscale=True)
    twice = derive(once, lambda d: cv2.resize(d, (640, 480)), (480, 640), {}, upscale=True)
    assert once.upscale_of is logged and twice.upscale_of is logged
    assert derive(twice, lambda d: d[::2, ::2], (240, 320), {}).upscale_of is None
