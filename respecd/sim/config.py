"""Profile section ``simulation:``: which scripted scenarios run, and the ranges their
random parameters are drawn from (domain randomization comes from sampling many seeds)."""

from __future__ import annotations

from pydantic import Field, field_validator, model_validator

from respecd.sensors import Intrinsics, StrictModel

# The six in-lab scenarios of the ReSPEC paper, in the order the paper runs them, then the
# one the paper motivates but does not stage: both cameras blind (a fabric curtain or a dense
# fog bank in front of everyone), only the radar sees.
PAPER_SCENARIOS: tuple[str, ...] = (
    "good-light-static",
    "poor-light-static",
    "good-light-moving",
    "poor-light-moving",
    "occlusion-partial",
    "occlusion-smoke",
)
SCENARIOS: tuple[str, ...] = (*PAPER_SCENARIOS, "behind-curtain")

# A 70-degree horizontal field of view at 1280x720 (close to a D435i/UVC colour camera).
DEFAULT_RGB_INTRINSICS = Intrinsics(fx=914.0, fy=914.0, cx=640.0, cy=360.0, width=1280, height=720)

Range = tuple[float, float]


class SimulationConfig(StrictModel):
    """The seeded world every simulated sensor of one daemon shares."""

    scenarios: list[str] = Field(
        default_factory=lambda: list(SCENARIOS),
        min_length=1,
        description="Scenarios to run in sequence (default: the ReSPEC paper's six in its order, then behind-curtain).",
    )
    scenario_duration_s: float = Field(30.0, gt=0, le=86400, description="Seconds each scenario lasts.")
    loop: bool = Field(
        True,
        description="Start over after the last scenario, with fresh random parameters; false holds the last one.",
    )
    seed: int | None = Field(None, ge=0, description="World seed; null uses the daemon's --seed.")
    people: tuple[int, int] = Field((1, 3), description="Fewest and most people per scenario.")
    distance_m: Range = Field((2.0, 12.0), description="Nearest and farthest distance of a person from the rover (m).")
    walk_speed_mps: Range = Field((0.5, 1.8), description="Walking speed range in the moving scenarios (m/s).")
    good_light: Range = Field((0.6, 1.0), description="Illumination range (0 dark .. 1 bright) in good light.")
    poor_light: Range = Field(
        (0.001, 0.008),
        description="Illumination range in poor light: a lab with the lights off (0.001 ~ 0.5 lux, 1 ~ office light).",
    )
    ego_speed_mps: Range = Field(
        (0.0, 0.4), description="Peak speed of the rover's own back-and-forth motion in the moving scenarios (m/s)."
    )
    camera_height_m: float = Field(0.45, gt=0.05, le=3, description="Height of the sensor head above the floor (m).")
    rgb_intrinsics: Intrinsics = Field(
        DEFAULT_RGB_INTRINSICS,
        description="Pinhole model of the simulated RGB camera; every simulated imager shares this view.",
    )
    max_exposure_s: float = Field(
        0.1,
        gt=0,
        le=1,
        description="Longest RGB auto-exposure (s; UVC cameras stop near 1/10 s); below that, one frame period.",
    )

    @field_validator("scenarios")
    @classmethod
    def _known_scenarios(cls, names: list[str]) -> list[str]:
        unknown = [n for n in names if n not in SCENARIOS]
        if unknown:
            raise ValueError(f"unknown scenario(s) {', '.join(unknown)} (expected: {', '.join(SCENARIOS)})")
        return names

    @model_validator(mode="after")
    def _ordered_ranges(self) -> SimulationConfig:
        for name in ("people", "distance_m", "walk_speed_mps", "good_light", "poor_light", "ego_speed_mps"):
            low, high = getattr(self, name)
            if low > high or low < 0:
                raise ValueError(f"{name}: expected [low, high] with 0 <= low <= high, got [{low}, {high}]")
        if self.people[0] < 1 or self.people[1] > 8:
            raise ValueError("people: expected between 1 and 8 people")
        if self.distance_m[0] < 1.0:
            raise ValueError("distance_m: people nearer than 1 m are not simulated")
        if self.good_light[1] > 1 or self.poor_light[1] > 1:
            raise ValueError("light levels are between 0 and 1")
        return self
