"""``python -m respecd.cli``: the same entry point as the ``respecd`` console script."""

from respecd.cli import entry

entry()
