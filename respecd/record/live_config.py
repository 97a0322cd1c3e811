"""Profile section ``live:``: how the Foxglove live view (``--foxglove``) guards its port.

The view has no authentication, so it is treated as a public surface: a handshake must
complete in time, connections are capped, a viewer that stops reading is dropped.
"""

from __future__ import annotations

from pydantic import Field

from respecd.sensors import StrictModel

MAX_CLIENTS = 256  # the unit's LimitNOFILE=4096 holds 3 descriptors a viewer at this cap, and the rest


class LiveConfig(StrictModel):
    max_clients: int = Field(
        32, ge=1, le=MAX_CLIENTS, description="Viewers (and handshakes in progress) at once; more are answered "
        "503 and closed. Each costs 3 file descriptors and up to backlog messages of memory.",
    )
    handshake_timeout_s: float = Field(
        5.0, gt=0, le=60, description="A connection must complete its WebSocket handshake within this many "
        "seconds, else it is closed (half-open connections cannot pile up).",
    )
    stall_s: float = Field(
        10.0, gt=0, le=300, description="A viewer that takes nothing from its socket for this long is dropped "
        "(logged once); a slow one loses its oldest messages instead (backlog).",
    )
    backlog: int = Field(
        16, ge=4, le=1024, description="Messages queued per viewer before its oldest are dropped (about 0.5 s "
        "of the simulated rover's channels; each sensor frame is up to a few hundred kB).",
    )
