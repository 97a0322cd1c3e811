"""``respecd export CKPT --to onnx OUT``: a checkpoint's net as ONNX graphs, as the daemon runs them.

The folder holds one graph per part of the net (each backbone, fusion + neck + head, and
for the CSP net the neck and each level's head branches, which the attribution runs on
crops) with batch norms folded, for the CSP net each also as ``NAME.nchwc.onnx`` (what ONNX
Runtime's CPU provider loads: perception/blocked.py), and ``manifest.json`` (checkpoint hash, spec, each graph's
inputs and outputs). The daemon exports by itself into its state directory on the first
start with ``perception.runtime: onnxruntime|openvino``; this command is for running the
graphs elsewhere (e.g. ``trtexec`` on a Jetson) or looking at them (Netron). With ONNX
Runtime installed, each graph is checked against torch on the example input.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from respecd.outputs import check_output_dir


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("weights", metavar="CKPT", help="checkpoint: a path or builtin:NAME")
    parser.add_argument("--to", required=True, choices=("onnx",), help="format (onnx: opset 17, dynamic H and W)")
    parser.add_argument("out", metavar="OUT", type=Path, help="folder to write the graphs and manifest.json into")


def main(args: argparse.Namespace) -> int:
    check_output_dir("OUT", args.out)
    from respecd.perception import checkpoint, export

    path = checkpoint.resolve(args.weights)
    model, _ = checkpoint.load(args.weights)
    manifest = export.export(model, args.out, export.checkpoint_hash(path), args.weights)
    check = _check(model, args.out, manifest)
    for name, graph in manifest["graphs"].items():
        for file in export.graph_files(graph):
            size = (args.out / file).stat().st_size
            print(f"{args.out / file}: {name} ({', '.join(graph['inputs'])} -> "
                  f"{', '.join(graph['outputs'])}), {size / 1e6:.1f} MB{check.get(file, '')}")
    print(f"{args.out / export.MANIFEST}: {manifest['checkpoint']} sha256 {manifest['sha256'][:16]}..., "
          f"opset {manifest['opset']}")
    return 0


def _check(model, folder: Path, manifest: dict) -> dict[str, str]:
    """Per graph file, ``, max |onnxruntime - torch| = ...`` on an example input (nothing without ORT)."""
    try:
        import onnxruntime
    except ImportError:
        return {}
    import torch

    from respecd.perception import export

    found = {}
    channels = len(model.spec.channels)
    x = torch.rand(1, channels, *export.EXAMPLE_HW, generator=torch.Generator().manual_seed(1))
    for part in model.export_parts(x, torch.ones(1, channels - 3)):
        feeds = {n: t.contiguous().numpy() for n, t in zip(part.inputs, part.example, strict=True)}
        with torch.no_grad():
            want = part.module(*part.example)
        graph = manifest["graphs"][part.name]
        for file in export.graph_files(graph):
            session = onnxruntime.InferenceSession(str(folder / file), providers=["CPUExecutionProvider"])
            got = session.run(None, feeds)
            worst = max(float((torch.from_numpy(g) - w).abs().max()) for g, w in zip(got, want, strict=True))
            found[file] = f", max |onnxruntime - torch| = {worst:.1e}"
    return found
