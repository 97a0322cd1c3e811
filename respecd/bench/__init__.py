"""Benchmarks: ``respecd bench NAME`` prints figures and writes JSON.

Each entry names a module with ``add_arguments(parser)`` and ``run(args) -> dict``; the
dict is printed as ``key: value`` lines and written with ``--json OUT``.
"""

from __future__ import annotations

BENCHES: dict[str, str] = {
    "pipeline": "respecd.bench.pipeline",
    "drivers": "respecd.bench.drivers",
    "inference": "respecd.bench.inference",
    "controller": "respecd.bench.controller",
    "scenarios": "respecd.bench.scenarios",
    "sim": "respecd.bench.sim",
    "replay": "respecd.bench.replay",
}
