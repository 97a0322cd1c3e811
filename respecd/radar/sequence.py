"""Frame-number bookkeeping for the radar data port: lost frames, restarts, corrupt numbers.

The demo numbers its frames 1, 2, 3, ... from ``sensorStart``. A number out of sequence is
either real (frames lost on the UART, or the sensor restarted) or one corrupted header
field; a single flipped bit must not turn into 2^31 lost frames. So an out-of-sequence
number is only a *suspect* until the next frame tells: ``suspect + 1`` confirms it (the
gap is counted then, on that frame), while a frame that continues the old sequence shows
it was corrupt (it still counts as a frame that arrived). Gaps are therefore reported one
frame late, and always exact when at most one number in a row is damaged.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class SequenceCounts:
    gaps: int = 0  # confirmed places where frame numbers jumped forward
    missing_frames: int = 0  # frames lost in those jumps
    restarts: int = 0  # confirmed jumps backwards (the sensor restarted)
    corrupt_numbers: int = 0  # out-of-sequence numbers the next frame did not confirm


class FrameSequence:
    """Feed each packet's frame number in stream order; ``advance`` returns frames lost before it."""

    def __init__(self, counts: SequenceCounts) -> None:
        self.counts = counts
        self._last: int | None = None  # last number known to be in sequence
        self._suspect: int | None = None  # an out-of-sequence number awaiting confirmation
        self._unconfirmed = 0  # frames that arrived after _last with numbers judged corrupt

    def advance(self, number: int) -> int:
        last, suspect = self._last, self._suspect
        if last is None or (suspect is None and number == last + 1):
            self._last = number
            return 0
        if suspect is None:
            self._suspect = number
            return 0
        if number == suspect + 1:
            return self._confirm(number)
        self.counts.corrupt_numbers += 1
        self._unconfirmed += 1
        if number == last + 1 + self._unconfirmed:  # the old sequence goes on: the suspect was corrupt
            self._settle(number)
        else:
            self._suspect = number
        return 0

    def _confirm(self, number: int) -> int:
        """The suspect was real: a jump forward (frames lost) or back (a restart)."""
        assert self._last is not None and self._suspect is not None
        missing = 0
        if self._suspect > self._last:
            missing = max(0, self._suspect - self._last - 1 - self._unconfirmed)
            if missing:
                self.counts.gaps += 1
                self.counts.missing_frames += missing
        else:
            self.counts.restarts += 1
        self._settle(number)
        return missing

    def _settle(self, number: int) -> None:
        self._last, self._suspect, self._unconfirmed = number, None, 0
