"""Start-up's objects out of the garbage collector's sight while a pipeline runs.

What start-up made (modules, the detector, the profile) lives as long as the run. Frozen
(``gc.freeze``) once the pipeline is up, a full collection scans only what the run allocated
since: with torch loaded one took tens of ms, holding the GIL on the loop or a stage's thread.
The live daemon and the replay both do it, and unfreeze after only what they froze.
"""

from __future__ import annotations

import gc


class StartupFreeze:
    """``up`` when the pipeline is up, ``release`` when the run is over (a no-op if something
    outside had frozen objects already: theirs stay frozen)."""

    def __init__(self, collect: bool = True) -> None:
        self._collect = collect  # collect the garbage of start-up first (the daemon; a replay's clock is running)
        self._froze = False

    def up(self) -> None:
        self._froze = gc.get_freeze_count() == 0
        if self._collect:
            gc.collect()
        gc.freeze()

    def release(self) -> None:
        if self._froze:
            gc.unfreeze()
        self._froze = False
