"""Profile section ``live:``: how the Foxglove live view (``--foxglove``) guards its port.

The view has no authentication, so it is treated as a public surface: a handshake must
complete in time, connections are capped, a viewer that stops reading is dropped, and a
browser page may connect only from an allowed origin — a page on the operator's laptop
(any site) could otherwise open ``ws://robot:8765`` and read the robot's cameras.
"""

from __future__ import annotations

from urllib.parse import urlsplit

from pydantic import Field, field_validator

from respecd.sensors import StrictModel

# Foxglove's web app, its desktop app (its pages load from file://) and pages served from this
# machine's loopback (any port). A client that sends no Origin is no browser page: it passes.
DEFAULT_ORIGINS = ("https://app.foxglove.dev", "file://", "http://localhost", "https://localhost",
                   "http://127.0.0.1", "https://127.0.0.1", "http://[::1]", "https://[::1]")
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
    queue_mib: float = Field(
        8.0, gt=0, le=1024, description="MiB of messages waiting for the live view's own thread (which hands each to "
        "every viewer) before the oldest are dropped: viewers never cost the recording or the control loop, and a "
        "starved view holds no more than this.",
    )
    allowed_origins: list[str] = Field(
        list(DEFAULT_ORIGINS), description="Browser origins (scheme://host[:port]; without a port any port) "
        "whose pages may connect; '*' allows any. A client that sends no Origin header is not a browser page "
        "and is always let in.",
    )

    @field_validator("allowed_origins")
    @classmethod
    def _origins(cls, value: list[str]) -> list[str]:
        for entry in value:
            if entry != "*" and not _is_origin(entry):
                raise ValueError(f"{entry!r} is not an origin: expected scheme://host[:port] (e.g. "
                                 "https://app.foxglove.dev, http://localhost:8080), file:// or '*'")
        return value


def _is_origin(entry: str) -> bool:
    key = _origin_key(entry)
    return key is not None and bool(key[0]) and (bool(key[1]) or key[0] == "file")


def _origin_key(text: str) -> tuple[str, str, int | None] | None:
    """(scheme, host, port) of an origin; None when it is not one (a path, a port that is no number)."""
    try:
        parts = urlsplit(text.strip().lower())
        port = parts.port
    except ValueError:
        return None
    if parts.path not in ("", "/") or parts.query or parts.fragment:
        return None
    return parts.scheme, parts.hostname or "", port


def origin_allowed(origin: str, allowed: list[str] | tuple[str, ...]) -> bool:
    """Whether a browser page from ``origin`` (the Origin header's value) may connect: an entry
    without a port allows every port of its scheme and host. ``null`` (a sandboxed or local page
    in some browsers) passes only ``*``."""
    if "*" in allowed:
        return True
    got = _origin_key(origin)
    if got is None or not got[0]:
        return False
    for entry in allowed:
        want = _origin_key(entry)
        if want is not None and want[:2] == got[:2] and want[2] in (None, got[2]):
            return True
    return False
