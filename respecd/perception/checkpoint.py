"""Checkpoints: a state dict plus the model spec in one ``torch.save`` file, and a JSON card.

Loading uses ``torch.load(weights_only=True)``: a checkpoint is data, never code. Every
way a file can be wrong (missing, not a torch file, not ours, another network shape)
becomes a one-line ``ConfigError`` naming the file and what differs.
"""

from __future__ import annotations

import json
import os
import pickle
import re
import warnings
import zipfile
from pathlib import Path
from typing import Any

import torch
from pydantic import ValidationError

from respecd import filekind
from respecd.errors import ConfigError
from respecd.perception.config import ModelSpec, resolve_weights
from respecd.perception.darknet_fusion import DarknetFusionNet
from respecd.perception.model import FusionNet, count_parameters

Net = FusionNet | DarknetFusionNet  # what a spec builds: the CSP net or the pretrained-Darknet variant

FORMAT = "respecd-fusion/1"


def resolve(source: str) -> Path:
    """'builtin:NAME' -> the packaged weights file; anything else is a path."""
    return resolve_weights(source)


def build(spec: ModelSpec) -> Net:
    """The network a spec describes: the CSP net, or the Darknet-backbone variant."""
    if spec.backbone.startswith("darknet:"):
        return DarknetFusionNet(spec)
    return FusionNet(spec)


def save(path: Path, model: Net, extra: dict[str, Any] | None = None) -> None:
    """Write the checkpoint atomically (tmp file + rename), so a crash never leaves half a file."""
    payload = {"format": FORMAT, "spec": model.spec.model_dump(mode="json"), "state_dict": model.state_dict()}
    payload.update(extra or {})
    save_payload(path, payload)


def save_payload(path: Path, payload: dict[str, Any]) -> None:
    """Write a checkpoint dict as ``read`` returns it, atomically (``save``)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    torch.save(payload, tmp)
    os.replace(tmp, path)


def write_card(path: Path, model: Net, card: dict[str, Any]) -> Path:
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
    zipped = _check_kind(path)
    try:
        with warnings.catch_warnings():  # torch warns about pickle protocols of files it then refuses
            warnings.simplefilter("ignore")
            payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # torch raises RuntimeError, UnpicklingError, EOFError... for bad files
        raise ConfigError(f"{path}: not a loadable torch checkpoint ({load_problem(err, zipped)})") from err
    if not isinstance(payload, dict) or payload.get("format") != FORMAT:
        raise ConfigError(f"{path}: not a respecd fusion checkpoint (expected format {FORMAT!r})")
    return payload


EXPECTED = "expected a respecd checkpoint written by `respecd train` (a torch zip archive)"


def _check_kind(path: Path) -> bool:
    """Refuse, from its first bytes, a file that is no torch file at all: torch would try it as a
    legacy pickle and call random bytes, a YAML or an ONNX model a file of Python objects.
    True: a torch zip archive; False: a pickle (torch's legacy format)."""
    if path.is_dir():
        raise ConfigError(f"{path}: is a directory, {EXPECTED}")
    if not path.is_file():
        raise ConfigError(f"{path}: no such checkpoint file")
    try:
        head = filekind.read_head(path)
    except OSError as err:
        raise ConfigError(f"{path}: cannot read checkpoint: {err.strerror or err}") from err
    if not head:
        raise ConfigError(f"{path}: empty file (0 bytes), {EXPECTED}")
    if filekind.is_pickle(head):
        return False  # torch.save's legacy format, or a plain pickle: torch.load(weights_only) decides
    if head.startswith(filekind.ZIP_MAGIC) and _torch_zip(path, head):
        return True  # torch's zip format (whole, cut or damaged: torch.load says which)
    raise ConfigError(f"{path}: not a torch checkpoint: it looks like {filekind.describe(head, path)} "
                      f"(first bytes {head[:8]!r}); {EXPECTED}")


def _torch_zip(path: Path, head: bytes) -> bool:
    """A ZIP archive torch may read: it has a ``data.pkl`` member, or its directory is unreadable
    (cut or damaged: torch's own words then). An .npz of arrays is not one."""
    entry = filekind.first_zip_entry(head)
    if entry is not None and entry.endswith("data.pkl"):
        return True
    try:
        with zipfile.ZipFile(path) as archive:
            return any(name.endswith("data.pkl") for name in archive.namelist())
    except (zipfile.BadZipFile, OSError, ValueError):
        return entry is None or not entry.endswith(".npy")


def load_problem(err: BaseException, zipped: bool = False) -> str:
    """Why torch refused a file, in our words. Never torch's own advice: it suggests re-running with
    ``weights_only=False`` or allow-listing classes, which would run code from an untrusted file.
    ``zipped``: the file is a torch zip archive, so anything but its pickle's content is damage."""
    text = str(err)
    objects = isinstance(err, pickle.UnpicklingError) or "Weights only load failed" in text
    if zipped and not objects:
        return "damaged or truncated: not a readable torch zip archive"
    if objects:
        found = re.search(r"Unsupported global: GLOBAL ([\w.]+)", text)
        what = f", e.g. {found.group(1)}" if found else ""
        return (f"it holds Python objects{what}, not only tensors and plain data; respecd loads checkpoints "
                "as data and never runs code from them: re-export it with respecd train or checkpoint.save")
    if "PytorchStreamReader" in text or isinstance(err, (EOFError, KeyError)):
        return "damaged or truncated: not a readable torch zip archive"
    first = text.strip().split(". ")[0].splitlines()[0] if text.strip() else type(err).__name__
    return type(err).__name__ if "weights_only" in first or "safe_globals" in first else first


def spec_of(source: str) -> ModelSpec:
    """The model spec a checkpoint holds (tools take whatever net the file has)."""
    path = resolve(source)
    try:
        return ModelSpec.model_validate(read(path)["spec"])
    except (KeyError, ValidationError) as err:
        raise ConfigError(f"{path}: checkpoint has no valid model spec ({err.__class__.__name__})") from err


def load(source: str, expected: ModelSpec | None = None, map_location: str = "cpu") -> tuple[Net, dict]:
    """Model (eval mode) and the raw payload. ``expected``: the profile's spec, must match."""
    path = resolve(source)
    payload = read(path)
    try:
        spec = ModelSpec.model_validate(payload["spec"])
    except (KeyError, ValidationError) as err:
        raise ConfigError(f"{path}: checkpoint has no valid model spec ({err.__class__.__name__})") from err
    if expected is not None:
        _check_match(path, spec, expected)
    model = build(spec)
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
