"""A table given to ``fleet eval`` is checked once, before any replay: one learned for another
profile or layout is bad input (exit 2, naming what differs), not a failure of every log."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from respecd.control.persist import StoredTable, mismatch
from respecd.errors import InputError
from respecd.lab.fleet.logs import LogRef, local_copy
from respecd.lab.fleet.transitions import controller_for


def check_table(table: StoredTable, refs: Sequence[LogRef], profile: dict[str, Any] | None,
                policy: str | None) -> None:
    """InputError when ``table`` does not fit the fleet's profile (``profile``, else the first log's)."""
    from respecd.record.reader import open_log

    if policy not in (None, "exploit", "learn"):
        raise InputError(f"--table: {policy} uses no Q-table (exploit acts on it, learn starts from it)")
    first = refs[0]
    with local_copy(first) as path:
        replayed, controller = controller_for(open_log(path, warn=False), profile)
    why = mismatch(table.meta, controller.layout(), replayed.name)
    if why is not None:
        whose = "--profile's" if profile is not None else f"{first.name}'s recorded profile"
        raise InputError(f"--table {table.name}: the Q-table does not fit {whose}: {why}")
