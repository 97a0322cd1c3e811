"""Profile section ``perception:``."""

from __future__ import annotations

from pydantic import Field

from respecd.drivers.base import StrictModel


class PerceptionConfig(StrictModel):
    enabled: bool = Field(True, description="Run the detector; off leaves the controller on scene signals only.")
    weights: str = Field(
        "builtin:sim-rover",
        description="Checkpoint path, or 'builtin:NAME' for a checkpoint shipped inside the package.",
    )
    device: str = Field("cpu", description="Torch device: cpu, cuda, cuda:0.")
    score_threshold: float = Field(0.25, ge=0, le=1, description="Minimum confidence kept after NMS.")
    attribution_every_s: float = Field(
        1.0, gt=0, description="Seconds between contribution attributions (default: once per decision)."
    )
