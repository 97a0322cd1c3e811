"""Pinhole projection shared by every simulated imager, and the ground truth boxes.

Every simulated imager (RGB, thermal, depth) sees exactly the RGB camera's view: its
intrinsics are the RGB intrinsics scaled to its own width and height. Alignment between
modalities is therefore the identity (a resize), which is what a calibrated, registered
sensor head would give after re-projection.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from respecd.sensors import Intrinsics
from respecd.sim.state import Occluder, SceneState, Target

NEAR_M = 0.3  # nothing nearer than this is projected
# 9 x 17 sample points over a person's body, as fractions of width and height (built once)
_GRID_U, _GRID_V = (g.ravel() for g in np.meshgrid(np.linspace(-0.45, 0.45, 9), np.linspace(-0.47, 0.47, 17)))


@dataclass(frozen=True, slots=True)
class Camera:
    """Intrinsics at one output resolution."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    @classmethod
    def at(cls, intrinsics: Intrinsics, resolution: tuple[int, int]) -> Camera:
        sx, sy = resolution[0] / intrinsics.width, resolution[1] / intrinsics.height
        return cls(intrinsics.fx * sx, intrinsics.fy * sy, intrinsics.cx * sx, intrinsics.cy * sy, *resolution)

    def project(self, x: float, y: float, z: float) -> tuple[float, float]:
        return self.fx * x / z + self.cx, self.fy * y / z + self.cy

    def box(self, center: tuple[float, float, float], size: tuple[float, float]) -> tuple[float, float, float, float]:
        """Unclipped pixel box of an upright rectangle facing the camera."""
        x, y, z = center
        w, h = size
        x1, y1 = self.project(x - w / 2, y - h / 2, z)
        x2, y2 = self.project(x + w / 2, y + h / 2, z)
        return x1, y1, x2, y2

    def image_velocity(self, target: Target) -> tuple[float, float]:
        """Pixels per second of the target's centre on the image."""
        (x, y, z), (vx, vy, vz) = target.position, target.velocity
        return self.fx * (vx * z - x * vz) / (z * z), self.fy * (vy * z - y * vz) / (z * z)


def _samples(target: Target) -> tuple[np.ndarray, np.ndarray, float]:
    """Points spread over the person's body (x, y arrays at depth z)."""
    x, y, z = target.position
    w, h = target.size
    return x + _GRID_U * w, y + _GRID_V * h, z


def blocked_mask(
    xs: np.ndarray, ys: np.ndarray, zs: np.ndarray, occluders: tuple[Occluder, ...], kind: str
) -> np.ndarray:
    """True where the ray from the sensor origin to (x, y, z) crosses an occluder of ``kind``."""
    hit = np.zeros(np.shape(xs), dtype=bool)
    for occ in occluders:
        if occ.kind != kind:
            continue
        zo = occ.center[2]
        x1, y1, x2, y2 = occ.bounds()
        scale = zo / np.maximum(zs, 1e-6)
        px, py = xs * scale, ys * scale
        hit |= (zs > zo) & (px >= x1) & (px <= x2) & (py >= y1) & (py <= y2)
    return hit


def smoke_opacity(xs: np.ndarray, ys: np.ndarray, zs: np.ndarray, occluders: tuple[Occluder, ...]) -> np.ndarray:
    """RGB opacity of the smoke in front of each point (0 = clear)."""
    clear = np.ones(np.shape(xs), dtype=np.float64)
    for occ in occluders:
        if occ.kind == "smoke":
            clear[blocked_mask(xs, ys, zs, (occ,), "smoke")] *= 1.0 - occ.rgb_opacity
    return 1.0 - clear


def transmission(
    xs: np.ndarray, ys: np.ndarray, zs: np.ndarray, occluders: tuple[Occluder, ...]
) -> tuple[np.ndarray, np.ndarray]:
    """Share of visible light and of LWIR that reaches the cameras from each point through
    the smoke, fog and curtains in front of it (1 = clear); solids are ``blocked_mask``'s."""
    rgb = np.ones(np.shape(xs), dtype=np.float64)
    lwir = np.ones(np.shape(xs), dtype=np.float64)
    for occ in occluders:
        if occ.kind != "solid":
            behind = blocked_mask(xs, ys, zs, (occ,), occ.kind)
            rgb[behind] *= 1.0 - occ.rgb_opacity
            lwir[behind] *= occ.thermal_transmission
    return rgb, lwir


def _as_blocker(target: Target) -> Occluder:
    """A person as an opaque rectangle for visibility tests (0.8 of the width: arms and the leg gap)."""
    w, h = target.size
    return Occluder("solid", target.position, (0.8 * w, h), 1.0, 0.0, float("inf"), target.temperature_k, target.color)


def ground_truth(state: SceneState, rgb_resolution: tuple[int, int]) -> list[dict]:
    """Boxes of every person at least partly in view, in pixels at ``rgb_resolution``.

    ``visible`` is the share of the body that is in the frame and not behind a solid
    occluder or a nearer person; ``smoke`` the mean RGB opacity of smoke in front of the
    visible part; ``transmission`` the mean share of its light reaching the RGB and the
    thermal camera through smoke, fog and curtains (the radar sees through all three).
    """
    cam = Camera.at(state.intrinsics, rgb_resolution)
    out: list[dict] = []
    bodies = {tg.id: _as_blocker(tg) for tg in state.targets}
    has_smoke = any(occ.kind == "smoke" for occ in state.occluders)
    has_obscurant = any(occ.kind != "solid" for occ in state.occluders)
    for target in sorted(state.targets, key=lambda tg: tg.id):
        if target.position[2] <= NEAR_M:
            continue
        x1, y1, x2, y2 = cam.box(target.position, target.size)
        bx1, by1 = max(0.0, x1), max(0.0, y1)
        bx2, by2 = min(float(cam.width), x2), min(float(cam.height), y2)
        if bx2 <= bx1 or by2 <= by1:
            continue
        xs, ys, z = _samples(target)
        zs = np.full_like(xs, z)
        u, v = cam.fx * xs / z + cam.cx, cam.fy * ys / z + cam.cy
        seen = (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)
        others = tuple(body for tid, body in bodies.items() if tid != target.id)
        seen &= ~blocked_mask(xs, ys, zs, state.occluders + others, "solid")
        smoky = has_smoke and bool(seen.any())
        smoke = float(smoke_opacity(xs, ys, zs, state.occluders)[seen].mean()) if smoky else 0.0
        rgb_t, lwir_t = (1.0, 1.0)
        if has_obscurant:
            rgb, lwir = transmission(xs, ys, zs, state.occluders)
            part = seen if seen.any() else slice(None)  # a hidden person: what would reach us through it all
            rgb_t, lwir_t = float(rgb[part].mean()), float(lwir[part].mean())
        out.append(
            {
                "id": target.id,
                "box": (bx1, by1, bx2, by2),
                "visible": float(seen.mean()),
                "smoke": smoke,
                "transmission": {"rgb": rgb_t, "thermal": lwir_t},
                "distance_m": target.distance_m,
                "speed_mps": target.speed_mps,
            }
        )
    return out
