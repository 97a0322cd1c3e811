"""The Q-table that ships inside the package (``respecd/control/tables/default-qtable.npz``),
trained by ``respecd train-policy`` on the simulated rover with the default profile.

``load_shipped`` is the read-only fallback when the state directory holds no table, for
``--policy exploit`` and for ``learn`` with ``controller.warm_start`` (the default): unlike
``persist.load_into`` it never renames a file it cannot use (the shipped one may sit in a read-only
site-packages), it only says so and returns False.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path
from typing import Any

import structlog

from respecd.control.persist import fingerprint, read_table
from respecd.control.qlearning import QTable
from respecd.errors import InputError

log = structlog.get_logger(__name__)

SHIPPED_TABLE = "default-qtable.npz"


def shipped_table_path() -> Path:
    return Path(str(resources.files("respecd.control") / "tables" / SHIPPED_TABLE))


def load_shipped(table: QTable, layout: dict[str, Any], path: Path | None = None) -> bool:
    """Restore ``table`` from the shipped file if it was learned for ``layout``; True if loaded."""
    path = path or shipped_table_path()
    if not path.is_file():
        return False
    try:
        meta, q, visits = read_table(path)
    except InputError as err:
        log.warning("shipped_qtable_unreadable", path=str(path), error=str(err))
        return False
    if meta.get("fingerprint") != fingerprint(layout) or q.shape != table.shape:
        log.warning("shipped_qtable_mismatch", path=str(path), fingerprint=meta.get("fingerprint"))
        return False
    table.restore(q, visits, meta["updates"], meta["epsilon"])
    log.info("qtable_loaded", path=str(path), updates=table.updates, shipped=True)
    return True
