"""Pure renderers: (scene state, sensor setting, rng) -> the array a real driver would emit.

Layouts follow ``respecd.messages.Frame``. Every imager shares the RGB camera's view
(see ``camera.py``). Objects are painted far to near, so nearer ones hide farther ones.

Physics kept on purpose (the controller must be able to learn from it):
* RGB: auto-exposure up to the frame period and gain up to 4x; in the dark the gain runs
  out, so the image is dim and read/shot noise swamps the contrast. Motion blur spans
  image velocity x exposure, so a slower frame rate blurs more when light is short.
* thermal: centikelvin counts (kelvin x 100, like a radiometric Lepton's TLinear output);
  indifferent to light; solid occluders block it, smoke lets 15-35 % through, a curtain or
  a dense fog bank about 1 %.
* depth: z-depth in millimetres, valid 0.3-3 m (0 = invalid), noise growing with z^2; a
  curtain is a surface to it, smoke and fog scatter its projected pattern.
"""

from __future__ import annotations

import cv2
import numpy as np

from respecd.sim.camera import Camera, ground_truth
from respecd.sim.radar_model import render_radar
from respecd.sim.state import HEAD_EXTRA_K, Occluder, SceneState, Target
from respecd.sim.textures import (
    DEPTH_MAX_MM,
    DEPTH_MIN_MM,
    NOISE_STD,
    curtain_texture,
    depth_background,
    fabric,
    noise_slice,
    rgb_background,
    smoke_texture,
    thermal_background,
)

__all__ = ["ground_truth", "render_depth", "render_imu", "render_lepton", "render_radar", "render_rgb",
           "render_thermal"]

FULL_WELL_E = 2000.0  # electrons at reflectance 1, light 1, 1/30 s: a small-pixel UVC sensor
READ_NOISE_E = 20.0
AE_TARGET_DN = 110.0  # auto-exposure aims for this mean level
MAX_GAIN = 4.0
NETD_K = 0.05  # thermal noise-equivalent temperature difference (Lepton class: < 50 mK)
SKIN_BGR = (120, 150, 200)
_SHIFT = 4  # cv2 drawing with 4 fractional bits keeps small, far people smooth
_ONE = 1 << _SHIFT


def _pt(x: float, y: float) -> tuple[int, int]:
    return int(round(x * _ONE)), int(round(y * _ONE))


def draw_person(img: np.ndarray, cam: Camera, target: Target, values: tuple, origin: tuple[int, int] = (0, 0)) -> None:
    """Paint a person's silhouette (head, torso, legs) with ``values`` onto ``img``.

    ``origin`` is the image position of ``img[0, 0]`` (for drawing into a region of interest).
    """
    x1, y1, x2, y2 = cam.box(target.position, target.size)
    x1, x2, y1, y2 = x1 - origin[0], x2 - origin[0], y1 - origin[1], y2 - origin[1]
    w, h = x2 - x1, y2 - y1
    cx = (x1 + x2) / 2
    head_r = min(0.07 * h, 0.35 * w)
    head, torso, legs = values
    cv2.rectangle(img, _pt(x1 + 0.04 * w, y1 + 0.5 * h), _pt(cx - 0.05 * w, y2), legs, -1, cv2.LINE_8, _SHIFT)
    cv2.rectangle(img, _pt(cx + 0.05 * w, y1 + 0.5 * h), _pt(x2 - 0.04 * w, y2), legs, -1, cv2.LINE_8, _SHIFT)
    axes = _pt(w / 2, 0.2 * h)
    cv2.ellipse(img, _pt(cx, y1 + 2 * head_r + 0.18 * h), axes, 0, 0, 360, torso, -1, cv2.LINE_8, _SHIFT)
    cv2.rectangle(img, _pt(x1, y1 + 2 * head_r + 0.12 * h), _pt(x2, y1 + 0.55 * h), torso, -1, cv2.LINE_8, _SHIFT)
    cv2.circle(img, _pt(cx, y1 + head_r), int(round(head_r * _ONE)), head, -1, cv2.LINE_8, _SHIFT)


def _far_to_near(state: SceneState) -> list[Target | Occluder]:
    items: list[Target | Occluder] = [*state.targets, *state.occluders]
    items = [i for i in items if (i.position if isinstance(i, Target) else i.center)[2] > 0.3]
    return sorted(items, key=lambda i: -(i.position if isinstance(i, Target) else i.center)[2])


def _roi(cam: Camera, box: tuple[float, float, float, float], pad: float = 2) -> tuple[int, int, int, int] | None:
    x1, y1 = max(0, int(box[0] - pad)), max(0, int(box[1] - pad))
    x2, y2 = min(cam.width, int(box[2] + pad) + 1), min(cam.height, int(box[3] + pad) + 1)
    return (x1, y1, x2, y2) if x2 > x1 and y2 > y1 else None


def auto_exposure(scene_dn: float, light: float, max_exposure_s: float) -> tuple[float, float]:
    """(exposure s, gain): expose up to the frame period, then add gain up to MAX_GAIN."""
    needed_s = AE_TARGET_DN / max(scene_dn * light, 1e-6) / 30.0  # exposure reaching the target at gain 1
    exposure = float(np.clip(needed_s, 1e-4, max_exposure_s))
    gain = float(np.clip(AE_TARGET_DN / max(scene_dn * light * exposure * 30.0, 1e-6), 1.0, MAX_GAIN))
    return exposure, gain


def rgb_exposure(state: SceneState, resolution: tuple[int, int], max_exposure_s: float) -> dict[str, float]:
    """The exposure and gain ``render_rgb`` uses for this scene (for frame metadata)."""
    _, scene_dn = rgb_background(state.room, state.camera_height, Camera.at(state.intrinsics, resolution))
    exposure, gain = auto_exposure(scene_dn, state.light, max_exposure_s)
    return {"exposure_s": exposure, "gain": gain}


def _paint_person_rgb(canvas: np.ndarray, cam: Camera, target: Target, exposure_s: float) -> None:
    du, dv = cam.image_velocity(target)
    blur = (abs(du) * exposure_s, abs(dv) * exposure_s)  # pixels swept during the exposure
    roi = _roi(cam, cam.box(target.position, target.size), pad=2 + max(blur) / 2 + 1)
    if roi is None:
        return
    x1, y1, x2, y2 = roi
    labels = np.zeros((y2 - y1, x2 - x1), np.uint8)
    draw_person(labels, cam, target, (1, 2, 3), (x1, y1))
    legs = tuple(int(c * 0.55) for c in target.color)
    lut = np.zeros((256, 1, 3), np.uint8)  # label -> colour, applied by cv2.LUT (numpy indexing is 5x slower)
    lut[1:4, 0] = (SKIN_BGR, target.color, legs)
    colored = cv2.LUT(cv2.merge((labels, labels, labels)), lut)
    layer = cv2.multiply(colored, fabric(cam.height, cam.width)[y1:y2, x1:x2], scale=1 / 255)
    mask = cv2.compare(labels, 0, cv2.CMP_GT)  # type: ignore[call-overload]
    dst = canvas[y1:y2, x1:x2]
    if max(blur) < 1.0:
        cv2.copyTo(layer, mask, dst)
        return
    ksize = (max(1, int(round(blur[0]))), max(1, int(round(blur[1]))))  # a box along the motion path
    premult = cv2.blur(cv2.bitwise_and(layer, layer, mask=mask), ksize).astype(np.float32)
    alpha = cv2.blur(mask, ksize).astype(np.float32)[..., None] / 255.0
    dst[:] = np.clip(dst * (1.0 - alpha) + premult, 0, 255).astype(np.uint8)


def _paint_occluder_rgb(canvas: np.ndarray, cam: Camera, occ: Occluder) -> None:
    roi = _roi(cam, cam.box(occ.center, occ.size), pad=0)
    if roi is None:
        return
    x1, y1, x2, y2 = roi
    dst = canvas[y1:y2, x1:x2]
    if occ.kind == "smoke":
        smoke = smoke_texture(cam.height, cam.width, occ.color)[y1:y2, x1:x2]
        cv2.addWeighted(dst, 1.0 - occ.rgb_opacity, smoke, occ.rgb_opacity, 0.0, dst=dst)
        return
    if occ.kind == "curtain":  # hanging folds across the width, the weave of the cloth
        cloth = cv2.multiply(curtain_texture(cam.height, cam.width, occ.color)[y1:y2, x1:x2],
                             fabric(cam.height, cam.width)[y1:y2, x1:x2], scale=1 / 255)
        cv2.addWeighted(dst, 1.0 - occ.rgb_opacity, cloth, occ.rgb_opacity, 0.0, dst=dst)
        return
    dst[:] = occ.color
    plank = max(2, int(0.2 * cam.fy / occ.center[2]))  # 20 cm boards
    dst[::plank] = tuple(int(c * 0.6) for c in occ.color)


def render_rgb(
    state: SceneState, resolution: tuple[int, int], exposure_s: float, rng: np.random.Generator
) -> np.ndarray:
    """uint8 (H, W, 3) BGR. ``exposure_s`` is the longest exposure allowed (about 1 / rate)."""
    cam = Camera.at(state.intrinsics, resolution)
    background, scene_dn = rgb_background(state.room, state.camera_height, cam)
    exposure, gain = auto_exposure(scene_dn, state.light, exposure_s)
    canvas = background.copy()
    for item in _far_to_near(state):
        if isinstance(item, Target):
            _paint_person_rgb(canvas, cam, item, exposure)
        else:
            _paint_occluder_rgb(canvas, cam, item)
    e_rel = exposure * 30.0  # exposure relative to 1/30 s
    signal = state.light * e_rel * gain  # DN out per DN of reflectance
    electrons = scene_dn / 255.0 * state.light * e_rel * FULL_WELL_E
    sigma_dn = gain * 255.0 / FULL_WELL_E * float(np.sqrt(electrons + READ_NOISE_E**2))
    beta = sigma_dn / NOISE_STD
    noise = noise_slice(rng, cam.height, cam.width)
    return cv2.addWeighted(canvas, signal, noise, beta, -128.0 * beta)


def _paint_occluder_scalar(img: np.ndarray, cam: Camera, occ: Occluder, solid_value: float, smoke_fn,
                           translucent_curtain: bool) -> None:
    """A solid fills its box with ``solid_value``; smoke (a curtain too, if translucent) goes to ``smoke_fn``."""
    roi = _roi(cam, cam.box(occ.center, occ.size), pad=0)
    if roi is None:
        return
    x1, y1, x2, y2 = roi
    if occ.kind == "solid" or (occ.kind == "curtain" and not translucent_curtain):
        img[y1:y2, x1:x2] = solid_value
    else:
        smoke_fn(img[y1:y2, x1:x2], (x1, y1, x2, y2))


def render_thermal(state: SceneState, resolution: tuple[int, int], rng: np.random.Generator) -> np.ndarray:
    """uint16 (H, W) centikelvin (counts = kelvin x 100)."""
    cam = Camera.at(state.intrinsics, resolution)
    temp = thermal_background(state.room, state.camera_height, cam).copy()
    for item in _far_to_near(state):
        if isinstance(item, Target):
            t = item.temperature_k
            draw_person(temp, cam, item, (t + HEAD_EXTRA_K, t, t - 1.0))
        else:

            def smoke(view: np.ndarray, _roi: tuple, occ: Occluder = item) -> None:
                view *= occ.thermal_transmission
                view += (1.0 - occ.thermal_transmission) * occ.temperature_k

            _paint_occluder_scalar(temp, cam, item, item.temperature_k, smoke, translucent_curtain=True)
    temp = cv2.GaussianBlur(temp, (0, 0), 0.7 * resolution[0] / 160)  # lens + detector MTF
    temp += rng.standard_normal(temp.shape, dtype=np.float32) * NETD_K  # type: ignore[arg-type]
    return np.clip(np.round(temp * 100.0), 0, 65535).astype(np.uint16)


LEPTON_NATIVE = (160, 120)  # the FLIR One Pro's thermal core; its 320x240 output is an upscale


def render_lepton(state: SceneState, size: tuple[int, int], rng: np.random.Generator) -> np.ndarray:
    """What the FLIR One delivers at ``size``: the 160x120 frame, bilinearly upscaled if larger (as drivers/flirone)."""
    native = render_thermal(state, LEPTON_NATIVE, rng)
    return native if tuple(size) == LEPTON_NATIVE else cv2.resize(native, tuple(size), interpolation=cv2.INTER_LINEAR)


def render_depth(state: SceneState, resolution: tuple[int, int], rng: np.random.Generator) -> np.ndarray:
    """uint16 (H, W) z-depth in millimetres; 0 where invalid (outside 0.3-3 m, dropouts, smoke)."""
    cam = Camera.at(state.intrinsics, resolution)
    depth = depth_background(state.room, state.camera_height, cam).copy()
    noise = noise_slice(rng, cam.height, cam.width)
    for item in _far_to_near(state):
        if isinstance(item, Target):
            z = item.position[2]
            draw_person(depth, cam, item, (z - 0.08, z, z))  # the head is rounder, a little nearer
        else:

            def smoke(view: np.ndarray, roi: tuple, occ: Occluder = item) -> None:
                x1, y1, x2, y2 = roi  # smoke scatters the IR pattern: stereo matching fails
                view[noise[y1:y2, x1:x2, 2] < 128 + NOISE_STD * (2 * occ.rgb_opacity - 1.3)] = 0.0

            _paint_occluder_scalar(depth, cam, item, item.center[2], smoke, translucent_curtain=False)
    # stereo RMS error ~ z^2 * subpixel / (focal * baseline) = 0.0025 z^2 m for a D435-class camera;
    # OpenCV calls on whole planes: this is the costliest per-pixel work of the sim after RGB
    jitter_dn, dropout_dn, _ = cv2.split(noise)
    jitter = cv2.subtract(jitter_dn, 128, dtype=cv2.CV_32F)  # type: ignore[call-overload]  # N(0, NOISE_STD)
    spread = cv2.multiply(depth, depth, scale=2.5 / NOISE_STD)  # mm of error per unit jitter
    mm = cv2.scaleAdd(depth, 1000.0, cv2.multiply(spread, jitter))
    valid = cv2.inRange(mm, DEPTH_MIN_MM, DEPTH_MAX_MM)
    valid &= cv2.compare(dropout_dn, 128 + 2.3 * NOISE_STD, cv2.CMP_LT)  # type: ignore[call-overload,misc]  # ~1 % dropouts
    out = np.zeros(mm.shape, np.uint16)
    cv2.copyTo(mm.astype(np.uint16), valid, out)
    return out


def render_imu(state: SceneState, rng: np.random.Generator) -> np.ndarray:
    """float32 (6,) ax, ay, az (m/s^2), gx, gy, gz (rad/s) in the camera frame (y down).

    At rest the accelerometer reads -9.81 on y (it measures the floor pushing up); mecanum
    rollers shake the rover in proportion to its speed.
    """
    shake = 0.04 + 0.8 * state.ego_speed
    accel = np.array([0.0, -9.81, state.ego_accel]) + rng.standard_normal(3) * shake
    gyro = rng.standard_normal(3) * (0.003 + 0.05 * state.ego_speed)
    return np.concatenate([accel, gyro]).astype(np.float32)
