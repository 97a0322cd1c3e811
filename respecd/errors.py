"""The small exception tree every module raises from.

``DriverUnavailableError`` means "not ready, retry later" (missing device or SDK); the
supervisor retries it with backoff. ``ConfigError`` is fatal and becomes exit status 2.
"""

from __future__ import annotations


class RespecdError(Exception):
    """Root of every error respecd raises on purpose."""


class ConfigError(RespecdError):
    """A profile, checkpoint or input file is invalid. ``problems`` holds one line each."""

    def __init__(self, message: str, problems: list[str] | None = None) -> None:
        super().__init__(message)
        self.problems = problems or [message]


class InputError(RespecdError):
    """A file given on the command line is missing or malformed (exit 2)."""


class UndecodableImageError(ValueError):
    """A recorded image whose bytes do not decode: one damaged frame, not a damaged log (a
    replay reads on without it). A ValueError, as the decoders raised before it had a name."""


class DriverError(RespecdError):
    """A sensor driver failed."""


class DriverUnavailableError(DriverError):
    """The device or its SDK is absent right now; retry later."""


class DriverIOError(DriverError):
    """Reading from or writing to the device failed."""


class DriverTimeoutError(DriverError):
    """The device did not answer in time."""


def report(err: RespecdError, prog: str) -> int:
    """Print each of ``err``'s problems as ``prog: problem`` on stderr (a ConfigError may hold several);
    returns 2, the exit status of bad input."""
    import sys

    for problem in getattr(err, "problems", None) or [str(err)]:
        print(f"{prog}: {problem}", file=sys.stderr)
    return 2
