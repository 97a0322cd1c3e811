"""``blocked.for_export``: the CSP net as ``respecd export`` writes it for ONNX Runtime's blocked (NCHWc)
convolutions. It must compute what the net computes (torch here; the exported graphs in ONNX Runtime when
it is installed), with each rewritten C2f's halves a whole number of blocks and no channel split left."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from respecd.perception import blocked, checkpoint, export, fold
from respecd.perception.model import C2f
from respecd.perception.runtimes import installed

needs_ort = pytest.mark.skipif(not (installed("onnx") and installed("onnxruntime")),
                               reason="onnxruntime is not installed (pip install -e '.[onnx]')")


@pytest.fixture(scope="module")
def folded():
    model, _ = checkpoint.load("builtin:sim-rover")
    return fold.for_inference(model, torch.device("cpu"))


def example(hw: tuple[int, int] = (160, 224)) -> tuple[torch.Tensor, torch.Tensor]:
    x = torch.rand(1, 5, *hw, generator=torch.Generator().manual_seed(3))
    return fold.channels_last(x), torch.tensor([[1.0, 0.0]])  # thermal on, radar off


def test_the_blocked_net_computes_what_the_net_computes(folded) -> None:
    wide = blocked.for_export(folded)
    x, presence = example()
    with torch.no_grad():
        rgb, aux = folded.encode_rgb(x[:, :3]), folded.encode_aux(x[:, 3:], presence)
        want = folded.fuse(rgb, aux)
        got_rgb, got_aux = wide.encode_rgb(x[:, :3]), wide.encode_aux(x[:, 3:], presence)
        got = wide.fuse(got_rgb, got_aux)
        crop = folded._neck(rgb, aux)[0][:, :, 2:9, 3:11]
        want_branch, got_branch = folded.head.branches(0, crop), wide.head.branches(0, crop)
    for a, b in zip((*rgb, *aux, *want, *want_branch), (*got_rgb, *got_aux, *got, *got_branch), strict=True):
        assert a.shape == b.shape and torch.allclose(a, b, atol=1e-5, rtol=0)
    assert any(isinstance(m, C2f) for m in folded.modules())  # the net it was given is left as it was


def test_each_rewritten_c2f_is_whole_blocks_and_narrow_ones_stay(folded) -> None:
    halves = sorted({m.c for m in folded.modules() if isinstance(m, C2f)})
    assert halves == [8, 12, 16, 24, 32, 48, 64]  # sim-rover's C2f halves: 8, 12 and 24 are not whole blocks
    wide = blocked.for_export(folded)
    rewritten = [m for m in wide.modules() if isinstance(m, blocked.BlockedC2f)]
    assert len(rewritten) == sum(1 for m in folded.modules() if isinstance(m, C2f) and m.c != 8)
    for block in rewritten:
        convs = [block.cv1a, block.cv1b, *(c for b in block.m for c in (b.cv1, b.cv2))]
        assert all(c.conv.out_channels % blocked.BLOCK == 0 for c in convs)
        assert block.cv2.conv.in_channels % blocked.BLOCK == 0
    assert [m.c for m in wide.modules() if isinstance(m, C2f)] == [8]  # the aux stem's: padding would double it
    assert blocked.worth_blocking(12) and blocked.worth_blocking(24) and not blocked.worth_blocking(8)


def test_a_net_without_c2f_blocks_is_exported_as_it_is() -> None:
    model, _ = checkpoint.load("builtin:rgbt")
    assert blocked.for_export(model) is model


def test_only_onnxruntimes_cpu_provider_loads_the_blocked_graphs(tmp_path: Path) -> None:
    from respecd.perception.runtimes.onnxruntime import graph_file, providers

    graph = {"file": "net.onnx", export.NCHWC: "net.nchwc.onnx"}
    assert graph_file(graph, providers("cpu", tmp_path)) == "net.nchwc.onnx"
    for gpu in ("cuda", "tensorrt"):
        assert graph_file(graph, providers(gpu, tmp_path)) == "net.onnx"
    assert graph_file({"file": "net.onnx"}, providers("cpu", tmp_path)) == "net.onnx"  # a Darknet net's export


@needs_ort
def test_the_blocked_export_gives_the_plain_graphs_outputs(folded, tmp_path: Path) -> None:
    import onnx
    import onnxruntime as ort

    manifest = export.export(folded, tmp_path)
    assert all(export.NCHWC in g for g in manifest["graphs"].values())
    x, presence = example((192, 256))
    feeds = {"rgb": x[:, :3].contiguous().numpy(), "aux": x[:, 3:].contiguous().numpy(), "presence": presence.numpy()}
    net = manifest["graphs"]["net"]
    runs = [ort.InferenceSession(str(tmp_path / net[key]), providers=["CPUExecutionProvider"]).run(None, feeds)
            for key in ("file", export.NCHWC)]
    for want, got in zip(*runs, strict=True):
        assert want.shape == got.shape and np.abs(want - got).max() < 1e-4
    graph = onnx.load(str(tmp_path / net[export.NCHWC])).graph
    weights = {w.name: list(w.dims) for w in graph.initializer}
    halves = [weights[n.input[1]] for n in graph.node
              if n.op_type == "Conv" and ("/cv1a/" in n.name or "/m.0/" in n.name)]
    assert halves and all(w[0] % blocked.BLOCK == 0 for w in halves if w[1] != 8)
    channel_splits = [n for n in graph.node if n.op_type in ("Split", "Slice")
                      and n.name.startswith(("/rgb/", "/neck/td", "/neck/bu"))]
    assert not channel_splits  # only the aux backbone's narrow C2f (left as it was) still splits
