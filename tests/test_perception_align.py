"""Alignment into the RGB view with a known calibration: thermal homography, radar splats, depth."""

from __future__ import annotations

import math

import numpy as np
import pytest

from respecd.messages import Frame
from respecd.perception.align import Aligner, normalize_thermal
from respecd.perception.config import ModelSpec, PerceptionConfig
from respecd.sensors import Calibration, Extrinsics, Intrinsics

RGB_K = Intrinsics(fx=457.0, fy=457.0, cx=320.0, cy=180.0, width=640, height=360)
RGB_CAL = Calibration(intrinsics=RGB_K)


def _frame(modality: str, data: np.ndarray, **meta) -> Frame:
    return Frame(modality=modality, t=0.0, seq=0, data=data, meta=meta)  # type: ignore[arg-type]


def _rgb() -> Frame:
    return _frame("rgb", np.zeros((360, 640, 3), np.uint8))


def _centroid(plane: np.ndarray, threshold: float) -> tuple[float, float]:
    vs, us = np.nonzero(plane > threshold)
    weights = plane[vs, us]
    return float((us * weights).sum() / weights.sum()), float((vs * weights).sum() / weights.sum())


def test_thermal_hot_spot_lands_where_the_rgb_camera_sees_it() -> None:
    yaw = 3.0
    thermal_cal = Calibration(
        intrinsics=Intrinsics(fx=150.0, fy=150.0, cx=80.0, cy=60.0, width=160, height=120),
        extrinsics=Extrinsics(rotation_rpy_deg=(0.0, 0.0, yaw), translation_m=(0.10, 0.0, 0.0)),
    )
    config = PerceptionConfig(plane_depth_m=5.0)
    # a warm point on the 5 m plane, in the thermal camera's frame
    p_t = np.array([0.3, -0.2, 5.0])
    u_t, v_t = 150.0 * p_t[0] / p_t[2] + 80.0, 150.0 * p_t[1] / p_t[2] + 60.0
    img = np.full((120, 160), 29300, np.uint16)  # 20 C background, centikelvin
    img[int(round(v_t)) - 1 : int(round(v_t)) + 2, int(round(u_t)) - 1 : int(round(u_t)) + 2] = 31300
    # where the RGB camera sees that point: rotate (yaw about y) then translate, then project
    c, s = math.cos(math.radians(yaw)), math.sin(math.radians(yaw))
    p_r = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]) @ p_t + np.array([0.10, 0.0, 0.0])
    expected = (457.0 * p_r[0] / p_r[2] + 320.0, 457.0 * p_r[1] / p_r[2] + 180.0)

    aligned = Aligner(config, {"rgb": RGB_CAL, "thermal": thermal_cal}).align(
        {"rgb": _rgb(), "thermal": _frame("thermal", img)}
    )
    plane = aligned.tensor[3, :360, :640]
    background = (293.0 - 273.0) / 40.0
    u, v = _centroid(plane, background + 0.1)
    # centroid of the resampled 3x3 spot vs. the exact projection; one thermal pixel is ~3 RGB pixels
    assert u == pytest.approx(expected[0] + 0.5 * 457 / 150, abs=2.0)
    assert v == pytest.approx(expected[1] + 0.5 * 457 / 150, abs=2.0)
    assert aligned.presence.tolist() == [1.0, 0.0]  # thermal delivered, radar absent


def test_uncalibrated_thermal_is_taken_to_share_the_rgb_view() -> None:
    img = np.full((120, 160), 29300, np.uint16)
    img[:, :80] = 31300  # left half hot
    aligned = Aligner(PerceptionConfig()).align({"rgb": _rgb(), "thermal": _frame("thermal", img)})
    plane = aligned.tensor[3]
    assert plane[:360, :300].mean() > 0.9 and plane[:360, 340:640].mean() < 0.6
    assert aligned.tensor.shape == (5, 384, 640)  # padded to a multiple of 32
    assert not aligned.tensor[:, 360:].any()


def test_thermal_units() -> None:
    config = PerceptionConfig(thermal_range_k=(273.0, 313.0))
    kelvin = _frame("thermal", np.array([[273.0, 293.0, 400.0]], np.float32), units="K")
    assert normalize_thermal(kelvin, config).tolist() == [[0.0, 0.5, 1.0]]
    counts = _frame("thermal", np.array([[29300]], np.uint16))  # centikelvin
    assert normalize_thermal(counts, config)[0, 0] == pytest.approx(0.5)
    eight_bit = _frame("thermal", np.full((2, 2, 3), 255, np.uint8))  # LLVIP: 3-channel grey JPEG
    assert normalize_thermal(eight_bit, config).shape == (2, 2)


def test_radar_point_projects_through_extrinsics_and_near_wins() -> None:
    cal = Calibration(extrinsics=Extrinsics(translation_m=(0.0, 0.1, 0.0)))  # 10 cm below the RGB camera
    aligner = Aligner(PerceptionConfig(), {"rgb": RGB_CAL, "radar": cal})
    # TI frame: x right, y forward (boresight), z up; columns x, y, z, v, snr
    points = np.array([[0.5, 4.0, 0.2, 0.0, 30.0]], np.float32)
    aligned = aligner.align({"rgb": _rgb(), "radar": _frame("radar", points)})
    plane = aligned.tensor[4, :360, :640]
    u, v = 457 * 0.5 / 4 + 320, 457 * (-0.2 + 0.1) / 4 + 180
    assert plane[int(round(v)), int(round(u))] == pytest.approx(1.0)
    assert _centroid(plane, 0.0) == pytest.approx((u, v), abs=1.0)
    assert aligned.presence.tolist() == [0.0, 1.0]
    # two returns on one ray: the near, weak one is drawn over the far, strong one
    ray = np.array([[0.5, 4.0, 0.2, 0, 30.0], [0.25, 2.0, 0.15, 0, 0.0]], np.float32)  # same pixel at half range
    plane = aligner.align({"rgb": _rgb(), "radar": _frame("radar", ray)}).tensor[4, :360, :640]
    assert plane[int(round(v)), int(round(u))] == pytest.approx(0.25)


def test_radar_with_no_points_is_present_but_empty() -> None:
    aligned = Aligner(PerceptionConfig()).align({"rgb": _rgb(), "radar": _frame("radar", np.zeros((0, 5), np.float32))})
    assert aligned.presence.tolist() == [0.0, 1.0] and not aligned.tensor[4].any()


def test_depth_reprojection_shifts_by_the_baseline_parallax() -> None:
    spec = ModelSpec(aux_modalities=("thermal", "radar", "depth"))
    cal = Calibration(
        intrinsics=Intrinsics(fx=228.5, fy=228.5, cx=160.0, cy=90.0, width=320, height=180),
        extrinsics=Extrinsics(translation_m=(0.05, 0.0, 0.0)),
    )
    config = PerceptionConfig(model=spec, depth_max_m=10.0)
    wall = np.full((180, 320), 2000, np.uint16)  # a wall 2 m away, millimetres
    aligned = Aligner(config, {"rgb": RGB_CAL, "depth": cal}).align({"rgb": _rgb(), "depth": _frame("depth", wall)})
    plane = aligned.tensor[5, :360, :640]
    shift = 457 * 0.05 / 2.0  # the depth camera sits 5 cm right: everything moves ~11 px right
    assert not plane[:, : int(shift) - 2].any()
    assert np.allclose(plane[10:350, int(shift) + 3 : 630], 0.8, atol=1e-5)  # 1 - 2 m / 10 m
    assert aligned.presence.tolist() == [0.0, 0.0, 1.0]


def test_missing_rgb_uses_default_size_and_zero_planes() -> None:
    aligned = Aligner(PerceptionConfig()).align({})
    assert aligned.size == (640, 360)
    assert not aligned.tensor.any() and aligned.presence.tolist() == [0.0, 0.0]


def test_a_stalled_rgb_camera_leaves_the_aux_planes_on_its_own_pixel_grid() -> None:
    """Boxes are drawn and published in the RGB camera's pixels: when its frame drops out of a bundle
    (stalled, failed, undecodable) the thermal and radar planes stay on the grid it last delivered,
    so a radar-only box lands where the camera's image shows the person."""
    aligner = Aligner(PerceptionConfig(), {"rgb": RGB_CAL})
    points = _frame("radar", np.array([[0.5, 4.0, 0.2, 0.0, 30.0]], np.float32))
    hot = np.full((120, 160), 295.0, np.float32)
    hot[50:70, 90:100] = 305.0
    aux = {"radar": points, "thermal": _frame("thermal", hot, units="kelvin")}
    with_rgb = aligner.align({"rgb": _frame("rgb", np.zeros((720, 1280, 3), np.uint8)), **aux})
    without = aligner.align(aux)
    assert without.size == with_rgb.size == (1280, 720)
    np.testing.assert_array_equal(without.tensor[3:], with_rgb.tensor[3:])
    assert not without.tensor[:3].any()
    assert aligner.align(aux, rgb_size=(960, 540)).size == (960, 540)  # a caller that knows the size says it
    aligner.forget_rgb_size()  # a new session: back to the calibrated size, before any frame
    assert aligner.align(aux).size == (640, 360)
    calibrated_hd = Calibration(intrinsics=Intrinsics(fx=914.0, fy=914.0, cx=640.0, cy=360.0, width=1280, height=720))
    assert Aligner(PerceptionConfig(), {"rgb": calibrated_hd}).align(aux).size == (1280, 720)


def test_rgb_planes_are_r_g_b_over_255_and_padding_stays_zero() -> None:
    """The camera delivers BGR; the net's first three planes are R, G, B in 0..1, padded to a multiple of 32."""
    bgr = np.random.default_rng(3).integers(0, 256, (360, 640, 3), dtype=np.uint8)
    aligned = Aligner(PerceptionConfig()).align({"rgb": _frame("rgb", bgr)})
    assert aligned.tensor.shape[1:] == (384, 640)
    for plane, channel in zip(aligned.tensor[:3], (2, 1, 0), strict=True):
        np.testing.assert_array_equal(plane[:360], bgr[:, :, channel] / np.float32(255))
    assert not aligned.tensor[:3, 360:].any()
