"""A checkpoint's net as ONNX graphs, one per part (``parts.py``), for ONNX Runtime and OpenVINO.

``export`` folds the batch norms and writes each part the net lists (``export_parts``) as
``NAME.onnx`` with dynamic height and width, for the CSP net also as ``NAME.nchwc.onnx``
(``blocked.py``: the same outputs in fewer copies on ONNX Runtime's CPU provider), plus
``manifest.json``: the checkpoint's hash, the spec, each graph's files, inputs and outputs.
``cached`` keeps one such folder per checkpoint content under a cache folder (the daemon's
state directory), so that ``runtime: onnxruntime`` on a ``builtin:`` checkpoint needs no step
by hand: the first start exports (seconds), later starts reuse it. Torch's TorchScript-based
exporter is used (opset 17): it needs no package beyond torch, and the graphs are plain ONNX
any runtime reads.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import tempfile
import warnings
from pathlib import Path
from typing import Any

import structlog
import torch

from respecd.errors import ConfigError
from respecd.perception import blocked, fold
from respecd.perception.checkpoint import Net
from respecd.perception.config import ModelSpec
from respecd.perception.parts import Part

log = structlog.get_logger(__name__)

FORMAT = "respecd-onnx/2"  # bump when the parts or their names change: cached exports are then redone
OPSET = 17
EXAMPLE_HW = (384, 640)  # the example input's size; every graph takes any multiple of 32
MANIFEST = "manifest.json"
NCHWC = "nchwc"  # a graph's variant for MLAS's blocked layout (ONNX Runtime's CPU provider), where the net has one


NET_CODE = ("model.py", "darknet.py", "darknet_fusion.py", "parts.py", "fold.py", "blocked.py",  # what a graph is
            "export.py")


def code_hash() -> str:
    """SHA-256 of the modules that define the exported graphs: an export made by other code is not reused."""
    digest = hashlib.sha256(FORMAT.encode())
    for name in NET_CODE:
        digest.update((Path(__file__).parent / name).read_bytes())
    return digest.hexdigest()


def checkpoint_hash(path: Path) -> str:
    """SHA-256 of the checkpoint file's bytes (what an export is keyed by)."""
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def export(model: Net, out: Path, sha256: str = "", source: str = "") -> dict[str, Any]:
    """Write ``model``'s parts (batch norms folded) and the manifest into the folder ``out``; the manifest.

    ``model`` is folded in place (it is for inference after this)."""
    model = fold.for_inference(model, torch.device("cpu"))
    model.engine = None
    channels = len(model.spec.channels)
    x = torch.rand(1, channels, *EXAMPLE_HW, generator=torch.Generator().manual_seed(0))
    presence = torch.ones(1, channels - 3)
    out.mkdir(parents=True, exist_ok=True)
    graphs: dict[str, dict[str, Any]] = {}
    for part in model.export_parts(x, presence):
        _export_part(part, out / f"{part.name}.onnx")
        graphs[part.name] = {"file": f"{part.name}.onnx", "inputs": list(part.inputs), "outputs": list(part.outputs)}
    nchwc = blocked.for_export(model)
    if nchwc is not model:  # the same parts for ONNX Runtime's CPU provider (blocked.py)
        for part in nchwc.export_parts(x, presence):  # type: ignore[operator]
            _export_part(part, out / f"{part.name}.{NCHWC}.onnx")
            graphs[part.name][NCHWC] = f"{part.name}.{NCHWC}.onnx"
    manifest = {"format": FORMAT, "checkpoint": source, "sha256": sha256, "opset": OPSET, "torch": torch.__version__,
                "spec": model.spec.model_dump(mode="json"), "graphs": graphs}
    (out / MANIFEST).write_text(json.dumps(manifest, indent=2) + "\n", encoding="utf-8")
    return manifest


def _export_part(part: Part, path: Path) -> None:
    """One part as an ONNX graph: height and width of every 4-D tensor dynamic, the anchor count too."""
    with torch.no_grad():
        outputs = part.module(*part.example)
    axes: dict[str, dict[int, str]] = {}
    for name, tensor in (*zip(part.inputs, part.example, strict=True), *zip(part.outputs, outputs, strict=True)):
        if tensor.dim() == 4:
            axes[name] = {2: f"{name}_h", 3: f"{name}_w"}
        elif tensor.dim() == 3:
            axes[name] = {1: f"{name}_n"}
    example = tuple(t.contiguous() for t in part.example)
    with warnings.catch_warnings():  # the TorchScript exporter is deprecated in favour of torch.export's,
        warnings.simplefilter("ignore")  # which needs onnxscript and cannot trace the nets' cached branches
        torch.onnx.export(part.module, example, str(path), dynamo=False, opset_version=OPSET,
                          input_names=list(part.inputs), output_names=list(part.outputs), dynamic_axes=axes,
                          do_constant_folding=True)


def graph_files(graph: dict[str, Any]) -> list[str]:
    """The files of one part in a manifest: the plain graph, then its ``nchwc`` variant where there is one."""
    return [graph[key] for key in ("file", NCHWC) if key in graph]


def read_manifest(folder: Path, spec: ModelSpec | None = None) -> dict[str, Any]:
    """The manifest of an export folder, checked: format, the graphs present, the spec (when given)."""
    path = folder / MANIFEST
    try:
        manifest = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError as err:
        raise ConfigError(f"{folder}: no {MANIFEST}: not a folder written by `respecd export`") from err
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise ConfigError(f"{path}: unreadable export manifest ({err})") from err
    found = manifest.get("format") if isinstance(manifest, dict) else None
    if found != FORMAT or not isinstance(manifest.get("graphs"), dict):
        raise ConfigError(f"{path}: export format {found!r}, expected {FORMAT!r} (re-run `respecd export`)")
    files = [f for g in manifest["graphs"].values() for f in graph_files(g)]
    missing = [f for f in files if not (folder / f).is_file()]
    if missing:
        raise ConfigError(f"{folder}: the export lacks {', '.join(missing)}")
    if spec is not None and ModelSpec.model_validate(manifest["spec"]) != spec:
        raise ConfigError(f"{path}: exported from another net than the checkpoint's (spec differs)")
    return manifest


def cached(model: Net, checkpoint_path: Path, cache_root: Path, source: str = "") -> Path:
    """The export folder of this checkpoint's content (and this code's nets) under ``cache_root``, exported
    first if missing. Written into a temporary folder beside it and renamed, so a crash or a second daemon
    never leaves or reads half an export. ``model`` is folded in place when an export is needed."""
    sha = checkpoint_hash(checkpoint_path)
    folder = cache_root / f"{checkpoint_path.stem}-{sha[:16]}-{code_hash()[:8]}"
    if manifest_ok(folder, model.spec):
        return folder
    log.info("detector_exporting", weights=source or str(checkpoint_path), to=str(folder))
    try:
        cache_root.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{folder.name}-", dir=cache_root))
    except OSError as err:
        raise ConfigError(f"{cache_root}: cannot write the exported graphs there ({err.strerror or err})") from err
    try:
        export(model, tmp, sha, source)
        for older in cache_root.glob(f"{checkpoint_path.stem}-{sha[:16]}-*"):  # exported by other code
            shutil.rmtree(older, ignore_errors=True)
        os.replace(tmp, folder)
    except OSError as err:
        if manifest_ok(folder, model.spec):  # another process finished the same export first
            return folder
        raise ConfigError(f"{folder}: cannot write the exported graphs ({err.strerror or err})") from err
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return folder


def manifest_ok(folder: Path, spec: ModelSpec) -> bool:
    """Whether ``folder`` holds a complete export of a net with ``spec``."""
    try:
        read_manifest(folder, spec)
        return True
    except ConfigError:
        return False
