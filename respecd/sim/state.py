"""What the simulated world looks like at one instant: immutable, cheap to build, shared by
every renderer so that all modalities see the same people at the same time.

Coordinates are the RGB camera frame: x right, y down, z forward, metres; the floor is the
plane y = camera_height.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from respecd.sensors import Intrinsics

Vec3 = tuple[float, float, float]

HEAD_EXTRA_K = 2.5  # the uncovered face/head reads warmer than clothing on a thermal camera


@dataclass(frozen=True, slots=True)
class Target:
    """One person, modelled as an upright billboard facing the camera."""

    id: int
    position: Vec3  # body centre (m)
    velocity: Vec3  # relative to the rover (m/s)
    size: tuple[float, float]  # width, height (m)
    temperature_k: float  # clothing surface; the head is HEAD_EXTRA_K warmer
    color: tuple[int, int, int]  # clothing albedo, BGR 0..255 under full light
    speed_mps: float  # the person's own walking speed over the floor

    @property
    def distance_m(self) -> float:
        x, y, z = self.position
        return (x * x + y * y + z * z) ** 0.5


@dataclass(frozen=True, slots=True)
class Occluder:
    """An upright rectangle facing the camera: a crate or wall edge (solid), smoke, or a fabric curtain.

    What each kind passes follows the physics of each band (see docs/SIMULATOR.md): a solid
    blocks all three sensors; smoke scatters visible light, and LWIR less the finer it is;
    a curtain is opaque to visible light and to LWIR (the fabric absorbs 8-14 um and shows
    its own temperature) but thin fabric costs a 60 GHz radar only a few dB.
    """

    kind: Literal["solid", "smoke", "curtain"]
    center: Vec3
    size: tuple[float, float]  # width, height (m)
    rgb_opacity: float  # 1 = opaque; smoke 0.85..0.97, dense smoke ~0.99
    thermal_transmission: float  # share of the radiance behind that gets through (0 solid)
    radar_loss_db: float  # two-way loss (dB) for radar returns behind it (inf = blocks)
    temperature_k: float
    color: tuple[int, int, int]  # BGR under full light

    def bounds(self) -> tuple[float, float, float, float]:
        """x1, y1, x2, y2 in metres on the occluder's plane z = center[2]."""
        cx, cy, _ = self.center
        w, h = self.size
        return cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2


@dataclass(frozen=True, slots=True)
class Room:
    """Static surroundings of one scenario: colours, back wall, radar clutter reflectors."""

    wall_z: float  # distance of the back wall (m)
    wall_color: tuple[int, int, int]
    floor_color: tuple[int, int, int]
    ambient_k: float
    texture_seed: int
    reflectors: tuple[Vec3, ...]  # static radar scatterers (furniture, wall features)
    warm_spots: tuple[tuple[float, float, float, float], ...]  # u, v (0..1 of the view), radius (0..1), +kelvin


@dataclass(frozen=True, slots=True)
class SceneState:
    """The world at time ``t``; a pure function of (config, seed, t)."""

    t: float
    scenario: str
    segment: int  # index of the scenario run since t = 0 (keeps counting when looping)
    scenario_t: float  # seconds since this scenario started
    light: float  # 0 dark .. 1 bright
    targets: tuple[Target, ...]
    occluders: tuple[Occluder, ...]
    ego_speed: float  # rover speed over the floor (m/s)
    ego_accel: float  # rover acceleration along z (m/s^2), for the IMU
    camera_height: float  # metres above the floor
    room: Room
    intrinsics: Intrinsics  # the RGB camera; every simulated imager shares its view
