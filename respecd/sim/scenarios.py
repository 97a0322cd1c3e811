"""The scripted scenarios: what each paper scenario is made of, and how one run of a
scenario (a *segment*) draws its random parameters from the seed.

To add a scenario: add a ``ScenarioSpec`` to ``SPECS`` and its name to ``SCENARIOS`` in
``respecd/sim/config.py``. A segment is drawn once from ``rng`` and then evaluated in closed
form at any time, so the world stays a pure function of (config, seed, t).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np

from respecd.sim.config import SCENARIOS, SimulationConfig
from respecd.sim.state import Occluder, Room, Vec3


@dataclass(frozen=True, slots=True)
class ScenarioSpec:
    light: Literal["good", "poor"]
    moving: bool  # people walk (and the rover drives back and forth)
    occluder: Literal["solid", "smoke", "curtain"] | None
    max_distance_m: float | None = None  # nearer than the profile's far limit (an indoor curtain)
    sunlit: bool = False  # daylight through windows: a sun-warmed room where LWIR contrast fades


SPECS: dict[str, ScenarioSpec] = {
    # good light is daylight: the sun warms the room to about skin-and-clothing temperature
    "good-light-static": ScenarioSpec("good", False, None, sunlit=True),
    "poor-light-static": ScenarioSpec("poor", False, None),
    "good-light-moving": ScenarioSpec("good", True, None, sunlit=True),
    "poor-light-moving": ScenarioSpec("poor", True, None),
    "occlusion-partial": ScenarioSpec("good", False, "solid"),
    "occlusion-smoke": ScenarioSpec("good", False, "smoke"),
    # a curtain or room divider a metre or two in front of the people, in a room: people stand 2-8 m away
    "behind-curtain": ScenarioSpec("good", False, "curtain", max_distance_m=8.0),
}
assert set(SPECS) == set(SCENARIOS), "every scenario needs a spec"


@dataclass(frozen=True, slots=True)
class Walker:
    """A person walking A -> B -> A at constant speed (static when speed is 0)."""

    id: int
    a: tuple[float, float]  # (x, z) on the floor, metres
    b: tuple[float, float]
    speed: float  # m/s
    phase_s: float
    size: tuple[float, float]  # width, height (m)
    temperature_k: float
    color: tuple[int, int, int]

    def at(self, t: float) -> tuple[float, float, float, float]:
        """x, z, vx, vz at ``t`` seconds into the segment (a triangle wave along A-B)."""
        dx, dz = self.b[0] - self.a[0], self.b[1] - self.a[1]
        length = math.hypot(dx, dz)
        if self.speed <= 0 or length < 1e-6:
            return self.a[0], self.a[1], 0.0, 0.0
        travelled = (t + self.phase_s) * self.speed % (2 * length)
        ux, uz = dx / length, dz / length
        sign = 1.0 if travelled < length else -1.0
        s = travelled if sign > 0 else 2 * length - travelled
        return self.a[0] + ux * s, self.a[1] + uz * s, sign * ux * self.speed, sign * uz * self.speed


@dataclass(frozen=True, slots=True)
class Segment:
    """One run of one scenario, with everything random already drawn."""

    name: str
    light: float
    walkers: tuple[Walker, ...]
    occluders: tuple[Occluder, ...]
    ego_amplitude_m: float  # the rover oscillates along z: d(t) = A sin(w t + phi)
    ego_omega: float  # rad/s
    ego_phase: float
    room: Room

    def ego(self, t: float) -> tuple[float, float, float]:
        """Rover displacement (m), velocity (m/s) and acceleration (m/s^2) along z."""
        angle = self.ego_omega * t + self.ego_phase
        a, w = self.ego_amplitude_m, self.ego_omega
        return a * math.sin(angle), a * w * math.cos(angle), -a * w * w * math.sin(angle)


def _u(rng: np.random.Generator, bounds: tuple[float, float]) -> float:
    return float(rng.uniform(bounds[0], bounds[1]))


def _x_limit(config: SimulationConfig, z: float) -> float:
    """Half-width (m) of the RGB view at depth z, less a margin so people start in view."""
    k = config.rgb_intrinsics
    return 0.8 * z * (k.cx / k.fx)


def _floor_point(
    config: SimulationConfig, rng: np.random.Generator, z_range: tuple[float, float]
) -> tuple[float, float]:
    z = _u(rng, z_range)
    limit = _x_limit(config, z)
    return float(rng.uniform(-limit, limit)), z


# Clothing surface temperature (K). Indoors at 20-25 C it reads 28-32 C; in a sun-warmed room
# (30-35 C) clothing and the air meet near skin temperature: the LWIR "thermal crossover"
# where a person's contrast against the background fades to a fraction of a kelvin.
CLOTHING_K = {False: (301.0, 305.5), True: (304.0, 307.5)}
AMBIENT_K = {False: (293.0, 298.0), True: (303.0, 308.0)}


def _walkers(spec: ScenarioSpec, config: SimulationConfig, rng: np.random.Generator) -> tuple[Walker, ...]:
    count = int(rng.integers(config.people[0], config.people[1] + 1))
    near, far = config.distance_m
    distances = (near, min(far, max(near, spec.max_distance_m or far)))
    walkers: list[Walker] = []
    for i in range(count):
        for _ in range(20):  # keep people apart so one does not hide another entirely
            a = _floor_point(config, rng, distances)
            if all(math.hypot(a[0] - w.a[0], a[1] - w.a[1]) > 1.0 for w in walkers):
                break
        b, speed = a, 0.0
        if spec.moving:
            while math.hypot(b[0] - a[0], b[1] - a[1]) < 1.5:
                b = _floor_point(config, rng, distances)
            speed = _u(rng, config.walk_speed_mps)
        size = (_u(rng, (0.42, 0.6)), _u(rng, (1.5, 1.9)))
        color = tuple(int(c) for c in rng.integers(25, 230, size=3))
        walkers.append(Walker(i, a, b, speed, _u(rng, (0.0, 60.0)), size, _u(rng, CLOTHING_K[spec.sunlit]), color))  # type: ignore[arg-type]
    return tuple(walkers)


def _room(config: SimulationConfig, rng: np.random.Generator, ambient_k: float, sunlit: bool = False) -> Room:
    wall_z = config.distance_m[1] + _u(rng, (1.5, 5.0))
    reflectors: list[Vec3] = []
    for _ in range(int(rng.integers(15, 40))):
        on_wall = rng.random() < 0.5
        z = wall_z if on_wall else _u(rng, (2.0, wall_z))
        y = (
            _u(rng, (-1.5, config.camera_height_m))
            if on_wall
            else _u(rng, (config.camera_height_m - 1.0, config.camera_height_m))
        )
        reflectors.append((float(rng.uniform(-1.2, 1.2)) * z * 0.75, y, z))
    spots = tuple(
        (_u(rng, (0.05, 0.95)), _u(rng, (0.05, 0.6)), _u(rng, (0.02, 0.08)), _u(rng, (3.0, 15.0)))
        for _ in range(int(rng.integers(0, 4)))
    )
    if sunlit:  # sunlit patches of floor and wall, a few kelvin warmer or cooler (shade) than the air
        spots += tuple(
            (_u(rng, (0.0, 1.0)), _u(rng, (0.2, 1.0)), _u(rng, (0.04, 0.2)), _u(rng, (-2.0, 4.0)))
            for _ in range(int(rng.integers(3, 8)))
        )
    wall = tuple(int(c) for c in rng.integers(90, 210, size=3))
    floor = tuple(int(c) for c in rng.integers(40, 150, size=3))
    seed = int(rng.integers(0, 2**31 - 1))
    return Room(wall_z, wall, floor, ambient_k, seed, tuple(reflectors), spots)  # type: ignore[arg-type]


def _solid_occluder(config: SimulationConfig, rng: np.random.Generator, w: Walker, ambient_k: float) -> Occluder:
    """A crate hiding the lower body, or a wall edge hiding one side, of person ``w``."""
    x_p, z_p = w.a
    width_p, height_p = w.size
    z_o = z_p - _u(rng, (0.6, min(2.0, z_p - 1.0)))
    scale = z_o / z_p  # rays to the person cross the occluder plane at this scale
    floor_y = config.camera_height_m
    covered = _u(rng, (0.4, 0.7))
    if rng.random() < 0.5:  # crate: from the floor up to `covered` of the person's height
        top = (floor_y - covered * height_p) * scale
        size = (width_p * scale * 2.0, floor_y - top)
        center: Vec3 = (x_p * scale, (floor_y + top) / 2, z_o)
    else:  # wall edge: covers `covered` of the person's width from the left or right
        side = -1.0 if rng.random() < 0.5 else 1.0
        edge = (x_p + side * (width_p / 2 - covered * width_p)) * scale
        width = 1.5
        size = (width, floor_y + 1.6)
        center = (edge + side * width / 2, floor_y - size[1] / 2, z_o)
    color = tuple(int(c) for c in rng.integers(40, 160, size=3))
    return Occluder("solid", center, size, 1.0, 0.0, math.inf, ambient_k + _u(rng, (-0.5, 0.5)), color)  # type: ignore[arg-type]


def _smoke(
    config: SimulationConfig, rng: np.random.Generator, walkers: tuple[Walker, ...], ambient_k: float
) -> Occluder:
    """A smoke screen in front of everyone: blocks RGB, most of thermal; radar sees through."""
    nearest = min(w.a[1] for w in walkers)
    z_o = max(1.0, nearest - _u(rng, (0.5, 1.0)))
    xs = [w.a[0] * z_o / w.a[1] for w in walkers]
    x1, x2 = min(xs) - 0.8, max(xs) + 0.8
    height = config.camera_height_m + 2.2
    center = ((x1 + x2) / 2, config.camera_height_m - height / 2, z_o)
    shade = int(rng.integers(170, 225))
    return Occluder(
        "smoke",
        center,
        (x2 - x1, height),
        _u(rng, (0.85, 0.97)),
        _u(rng, (0.15, 0.35)),
        _u(rng, (1.0, 3.0)),
        ambient_k + _u(rng, (0.0, 2.0)),
        (shade, shade, shade),
    )


def _curtain(
    config: SimulationConfig, rng: np.random.Generator, walkers: tuple[Walker, ...], ambient_k: float
) -> Occluder:
    """What blinds both cameras but not a 60 GHz radar, in front of everyone: a curtain or a fog bank.

    A fabric curtain is opaque to visible light and to LWIR (cloth absorbs 8-14 um and shows
    its own, ambient temperature) while thin fabric costs a 60 GHz wave about 0.5-2 dB each
    way. A dense water fog scatters visible light and LWIR alike (its droplets are about the
    LWIR wavelength, unlike the sub-micron soot of smoke) and costs 60 GHz well under 1 dB
    over a few metres.
    """
    nearest = min(w.a[1] for w in walkers)
    z_o = max(1.0, nearest - _u(rng, (0.5, 1.5)))
    xs = [w.a[0] * z_o / w.a[1] for w in walkers]
    x1, x2 = min(xs) - _u(rng, (0.8, 2.0)), max(xs) + _u(rng, (0.8, 2.0))
    height = config.camera_height_m + 2.3  # floor to above anyone's head
    center = ((x1 + x2) / 2, config.camera_height_m - height / 2, z_o)
    if rng.random() < 0.5:
        color = tuple(int(c) for c in rng.integers(40, 220, size=3))
        loss_db = 2 * _u(rng, (0.5, 2.0))  # two-way
        return Occluder("curtain", center, (x2 - x1, height), 1.0, _u(rng, (0.0, 0.01)), loss_db,
                        ambient_k + _u(rng, (-0.3, 0.5)), color)  # type: ignore[arg-type]
    shade = int(rng.integers(190, 235))
    return Occluder("smoke", center, (x2 - x1, height), _u(rng, (0.985, 1.0)), _u(rng, (0.0, 0.01)),
                    _u(rng, (0.0, 0.5)), ambient_k + _u(rng, (-0.5, 0.5)), (shade, shade, shade))


def draw_segment(name: str, config: SimulationConfig, rng: np.random.Generator) -> Segment:
    """Draw every random parameter of one run of scenario ``name``."""
    spec = SPECS[name]
    light = _u(rng, config.good_light if spec.light == "good" else config.poor_light)
    ambient_k = _u(rng, AMBIENT_K[spec.sunlit])
    walkers = _walkers(spec, config, rng)
    occluders: tuple[Occluder, ...] = ()
    if spec.occluder == "solid":
        occluders = (_solid_occluder(config, rng, walkers[0], ambient_k),)
    elif spec.occluder == "smoke":
        occluders = (_smoke(config, rng, walkers, ambient_k),)
    elif spec.occluder == "curtain":
        occluders = (_curtain(config, rng, walkers, ambient_k),)
    omega = 2 * math.pi / _u(rng, (8.0, 15.0))
    amplitude = _u(rng, config.ego_speed_mps) / omega if spec.moving else 0.0
    amplitude = min(amplitude, 0.5 * (config.distance_m[0] - 0.5))  # never drive into the nearest person
    room = _room(config, rng, ambient_k, spec.sunlit)
    return Segment(name, light, walkers, occluders, amplitude, omega, _u(rng, (0, 2 * math.pi)), room)
