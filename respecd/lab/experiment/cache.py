"""The outcome cache: what the detector made of one set of frames, kept on disk.

Training runs thousands of controller steps; running the detector at each would take a
CPU hours. But the detector's outcome is a pure function of its input frames, and a frame
is a pure function of (world, modality, setting, frame time) — see ``frames.py``. So each
outcome is computed once and replayed whenever an episode, a policy or a later run asks
for the same frames again. Nothing learned changes: a replayed outcome is bit-for-bit the
one the detector would produce.

Keys and invalidation. A key is the SHA-256 of:
  * the *fingerprint*: hash of the detector's weights (its state dict, so a random model in
    a test and a checkpoint file are handled alike), the perception settings that shape
    the outcome (thresholds, attribution targets, calibration), the sources of the
    renderers, of the perception code and of the feature extractor (an outcome stores the
    scene features the state needs), and ``CACHE_VERSION``;
  * the world: simulation settings and seed;
  * the frames: one ``FrameId`` per detector input, and whether attribution ran.
Each fingerprint gets its own SQLite file ``outcomes-<fingerprint>.sqlite`` under
``$XDG_CACHE_HOME/respecd/experiment`` (default ``~/.cache/respecd/experiment``): a new
checkpoint or a code change starts an empty file and never reads a stale outcome. Delete
the folder to reclaim the space. Never inside the repository.
"""

from __future__ import annotations

import hashlib
import json
import os
import sqlite3
from importlib import resources
from pathlib import Path
from typing import Any

CACHE_VERSION = 1
# modules whose code decides what an outcome is: renderers, alignment, network, NMS, attribution,
# and the feature extractor whose scene features (luminance, motion) an outcome stores
SOURCE_MODULES = {
    "respecd.control": ("features.py", "imagestats.py"),
    "respecd.sim": ("camera.py", "radar_model.py", "render.py", "scenarios.py", "state.py", "textures.py",
                    "world.py"),
    "respecd.perception": ("ablation.py", "align.py", "attribution.py", "boxes.py", "calibration.py",
                           "darknet_fusion.py", "detector.py", "model.py", "split.py"),
    "respecd.lab.experiment": ("frames.py", "outcomes.py"),
}


def cache_dir() -> Path:
    base = os.environ.get("XDG_CACHE_HOME")
    return (Path(base) if base else Path.home() / ".cache") / "respecd" / "experiment"


def model_hash(model: Any) -> str:
    """SHA-256 over the state dict (names, shapes, dtypes, bytes) of a torch module."""
    digest = hashlib.sha256()
    for name, tensor in model.state_dict().items():
        t = tensor.detach().cpu().contiguous()
        digest.update(f"{name}:{tuple(t.shape)}:{t.dtype}".encode())
        digest.update(t.numpy().tobytes())
    return digest.hexdigest()


def source_hash() -> str:
    digest = hashlib.sha256()
    for package, names in SOURCE_MODULES.items():
        root = resources.files(package)
        for name in names:
            digest.update(name.encode())
            digest.update((root / name).read_bytes())
    return digest.hexdigest()


def fingerprint(weights_hash: str, perception: dict[str, Any], extra: dict[str, Any] | None = None) -> str:
    """16 hex digits naming everything an outcome depends on besides world and frames."""
    body = {"version": CACHE_VERSION, "weights": weights_hash, "perception": perception,
            "source": source_hash(), **(extra or {})}
    canonical = json.dumps(body, sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(canonical.encode()).hexdigest()[:16]


def outcome_key(fp: str, world_key: str, frame_keys: list[str], attribute: bool) -> str:
    canonical = json.dumps([fp, world_key, sorted(frame_keys), bool(attribute)], separators=(",", ":"))
    return hashlib.sha256(canonical.encode()).hexdigest()


class OutcomeCache:
    """Key -> JSON outcome, in memory and (unless ``path`` is None) in a SQLite file."""

    def __init__(self, path: Path | None) -> None:
        self.path = path
        self._mem: dict[str, dict[str, Any]] = {}
        self._db: sqlite3.Connection | None = None
        self._pending = 0
        self.hits = self.misses = 0
        if path is not None:
            path.parent.mkdir(parents=True, exist_ok=True)
            # several runs may share one file (a training and a benchmark): WAL lets readers
            # through while one writes, and every put commits at once so no lock is held long
            self._db = sqlite3.connect(path, timeout=60.0)
            self._db.execute("PRAGMA journal_mode=WAL")
            self._db.execute("CREATE TABLE IF NOT EXISTS outcomes (key TEXT PRIMARY KEY, value TEXT NOT NULL)")
            self._db.commit()

    @classmethod
    def for_fingerprint(cls, fp: str, directory: Path | None = None, enabled: bool = True) -> OutcomeCache:
        return cls((directory or cache_dir()) / f"outcomes-{fp}.sqlite" if enabled else None)

    def __len__(self) -> int:
        if self._db is None:
            return len(self._mem)
        return int(self._db.execute("SELECT COUNT(*) FROM outcomes").fetchone()[0])

    def get(self, key: str) -> dict[str, Any] | None:
        value = self._mem.get(key)
        if value is None and self._db is not None:
            row = self._db.execute("SELECT value FROM outcomes WHERE key = ?", (key,)).fetchone()
            if row is not None:
                value = json.loads(row[0])
                self._mem[key] = value
        if value is None:
            self.misses += 1
        else:
            self.hits += 1
        return value

    def put(self, key: str, value: dict[str, Any]) -> None:
        self._mem[key] = value
        if self._db is not None:
            self._db.execute("INSERT OR REPLACE INTO outcomes VALUES (?, ?)", (key, json.dumps(value)))
            self._pending += 1
            self.flush()  # an outcome costs ~1 s to compute; a commit costs ~1 ms

    def flush(self) -> None:
        if self._db is not None and self._pending:
            self._db.commit()
            self._pending = 0

    def close(self) -> None:
        if self._db is not None:
            self.flush()
            self._db.close()
            self._db = None
