"""Recording sessions to MCAP and replaying them; ``make_recorder`` is what a run asks for."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from respecd.clock import Clock

if TYPE_CHECKING:
    from respecd.config import Profile
    from respecd.record.recorder import Recorder


def make_recorder(profile: Profile, path: str | None, clock: Clock, foxglove: str | None = None,
                  **options: Any) -> Recorder | None:
    """The recorder when a log (``path`` or the profile's ``recording``) or the live view
    (``foxglove``, ``[HOST:]PORT``) is asked for; None when neither is. ``options``: the
    ``Recorder``'s keyword arguments (a replay's ``lossless``, ``origin``, ``metadata``)."""
    to_file = path is not None or profile.recording.enabled
    if not to_file and foxglove is None:
        return None
    from respecd.record.recorder import Recorder

    live = None
    if foxglove is not None:
        from respecd.record.live import LiveView, parse_address

        live = LiveView(*parse_address(foxglove), name=f"respecd {profile.name}", config=profile.live)
    config = profile.recording
    if path is not None:
        config = config.model_copy(update={"enabled": True, "path": path})
    return Recorder(config, profile, clock, live=live, to_file=to_file, **options)
