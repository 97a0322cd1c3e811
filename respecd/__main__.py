"""``python -m respecd``: the same entry point as the ``respecd`` console script."""

import sys

from respecd.cli import main

sys.exit(main())
