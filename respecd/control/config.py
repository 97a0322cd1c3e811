"""Profile section ``controller:``."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from respecd.drivers.base import StrictModel

Policy = Literal["learn", "exploit", "static", "heuristic"]


class ControllerConfig(StrictModel):
    enabled: bool = Field(True, description="Run the controller task.")
    policy: Policy = Field("learn", description="learn (online Q-learning), exploit (frozen table), static, heuristic.")
    decision_period_s: float = Field(1.0, gt=0, le=60, description="Seconds between decisions.")
