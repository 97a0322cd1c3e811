"""Benchmarks: ``respecd bench NAME`` prints figures and writes JSON.

Each entry names a module with ``add_arguments(parser)`` and ``run(args) -> dict``; the
dict is printed as ``key: value`` lines and written with ``--json OUT``.
"""

from __future__ import annotations

BENCHES: dict[str, str] = {
    "pipeline": "respecd.lab.bench.pipeline",
    "drivers": "respecd.lab.bench.drivers",
    "inference": "respecd.lab.bench.inference",
    "training": "respecd.lab.bench.training",
    "controller": "respecd.lab.bench.controller",
    "scenarios": "respecd.lab.bench.scenarios",
    "sim": "respecd.lab.bench.sim",
    "replay": "respecd.lab.bench.replay",
    "recording": "respecd.lab.bench.recording",
    "live": "respecd.lab.bench.live",
    "soak": "respecd.lab.bench.soak",
    "peers": "respecd.lab.bench.peers",
    "attacks": "respecd.lab.bench.attacks",
    "fleet": "respecd.lab.bench.fleet",
}
