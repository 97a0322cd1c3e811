"""The replay's progress bar: on a terminal only, its speed as "x real time"."""

from __future__ import annotations

import io
import os

import pytest

from respecd.replay.run import BAR_FORMAT, _progress_bar, progress_shown, speed_label


def test_the_bar_shows_on_a_terminal_only() -> None:
    leader, follower = os.openpty()
    with open(follower, "w") as terminal, open(leader, "rb", buffering=0):
        assert progress_shown(60.0, terminal)
        assert not progress_shown(10.0, terminal)  # too short to watch
    assert not progress_shown(60.0, io.StringIO())  # a pipe, a file, the journal
    with open(os.devnull, "w") as devnull:
        assert not progress_shown(60.0, devnull)


def test_speed_reads_as_times_real_time() -> None:
    assert speed_label(60.0, 20.0) == "3.0× real time"
    assert speed_label(0.0, 0.0) == "– × real time"
    pytest.importorskip("tqdm")
    out = io.StringIO()
    bar = _progress_bar()(total=60, unit="s", file=out, bar_format=BAR_FORMAT, mininterval=0, leave=True)
    bar.update(30)
    bar.close()
    text = out.getvalue()
    assert "× real time" in text and "30/60 s of log" in text and "s/s" not in text
