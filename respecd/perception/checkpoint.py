"""Checkpoints: a state dict plus the model spec in one ``torch.save`` file, and a JSON card.

Loading uses ``torch.load(weights_only=True)``: a checkpoint is data, never code. Every
way a file can be wrong (missing, not a torch file, not ours, another network shape)
becomes a one-line ``ConfigError`` naming the file and what differs.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import torch
from pydantic import ValidationError

from respecd.errors import ConfigError
from respecd.perception.config import ModelSpec, resolve_weights
from respecd.perception.model import FusionNet, count_parameters

FORMAT = "respecd-fusion/1"


def resolve(source: str) -> Path:
    """'builtin:NAME' -> the packaged weights file; anything else is a path."""
    return resolve_weights(source)


def save(path: Path, model: FusionNet, extra: dict[str, Any] | None = None) -> None:
    """Write the checkpoint atomically (tmp file + rename), so a crash never leaves half a file."""
    payload = {"format": FORMAT, "spec": model.spec.model_dump(mode="json"), "state_dict": model.state_dict()}
    payload.update(extra or {})
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    torch.save(payload, tmp)
    os.replace(tmp, path)


def write_card(path: Path, model: FusionNet, card: dict[str, Any]) -> Path:
    """The JSON model card beside the checkpoint: channels, widths, sizes, data, metrics."""
    body = {
        "format": FORMAT,
        "channels": list(model.spec.channels),
        "spec": model.spec.model_dump(mode="json"),
        "parameters": count_parameters(model),
        "checkpoint_bytes": path.stat().st_size if path.exists() else None,
        **card,
    }
    card_path = path.with_suffix(".json")
    card_path.write_text(json.dumps(body, indent=2) + "\n", encoding="utf-8")
    return card_path


def read(path: Path) -> dict[str, Any]:
    """The raw checkpoint dict, validated for format; ConfigError otherwise."""
    if not path.is_file():
        raise ConfigError(f"{path}: no such checkpoint file")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # torch raises RuntimeError, UnpicklingError, EOFError... for bad files
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise ConfigError(f"{path}: not a loadable torch checkpoint ({first})") from err
    if not isinstance(payload, dict) or payload.get("format") != FORMAT:
        raise ConfigError(f"{path}: not a respecd fusion checkpoint (expected format {FORMAT!r})")
    return payload


def load(source: str, expected: ModelSpec | None = None, map_location: str = "cpu") -> tuple[FusionNet, dict]:
    """Model (eval mode) and the raw payload. ``expected``: the profile's spec, must match."""
    path = resolve(source)
    payload = read(path)
    try:
        spec = ModelSpec.model_validate(payload["spec"])
    except (KeyError, ValidationError) as err:
        raise ConfigError(f"{path}: checkpoint has no valid model spec ({err.__class__.__name__})") from err
    if expected is not None:
        _check_match(path, spec, expected)
    model = FusionNet(spec)
    try:
        model.load_state_dict(payload["state_dict"])
    except (KeyError, RuntimeError) as err:
        detail = str(err).strip().splitlines()[0] if str(err).strip() else "missing state_dict"
        raise ConfigError(f"{path}: weights do not fit the model spec ({detail})") from err
    return model.to(map_location).eval(), payload


def _check_match(path: Path, found: ModelSpec, expected: ModelSpec) -> None:
    diffs = [
        f"perception.model.{name}: profile has {getattr(expected, name)!r}, checkpoint has {getattr(found, name)!r}"
        for name in ModelSpec.model_fields
        if getattr(found, name) != getattr(expected, name)
    ]
    if diffs:
        raise ConfigError(f"{path}: checkpoint does not match the profile ({'; '.join(diffs)})",
                          [f"{path}: checkpoint does not match the profile: {d}" for d in diffs])
