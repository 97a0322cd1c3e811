"""Profile section ``recording:``."""

from __future__ import annotations

from pydantic import Field

from respecd.drivers.base import StrictModel


class RecordingConfig(StrictModel):
    enabled: bool = Field(False, description="Record the session to MCAP.")
    path: str = Field("respecd-{time}.mcap", description="Output path; {time} becomes the start time.")
