"""``perception.runtime``'s plumbing: the profile's checks, the device -> execution provider mapping, a
runtime that is not installed (a one-line error, nothing exported), the export cache keyed by checkpoint
hash, and ``respecd export``. The export needs the onnx package; those tests skip without it."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import structlog
import yaml
from pydantic import ValidationError

from respecd.cli import main
from respecd.errors import ConfigError
from respecd.perception.config import PerceptionConfig
from respecd.perception.runtimes import installed

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
needs_onnx = pytest.mark.skipif(not installed("onnx"), reason="onnx is not installed (pip install -e '.[onnx]')")
needs_ort = pytest.mark.skipif(not (installed("onnx") and installed("onnxruntime")),
                               reason="onnxruntime is not installed (pip install -e '.[onnx]')")


@pytest.fixture(autouse=True)
def _fresh_logging():
    yield
    structlog.reset_defaults()


def test_a_lower_precision_or_gradients_need_the_right_runtime() -> None:
    with pytest.raises(ValidationError, match="precision bf16 needs runtime onnxruntime or openvino"):
        PerceptionConfig(precision="bf16")
    with pytest.raises(ValidationError, match="attribution_method gradient needs runtime torch"):
        PerceptionConfig(runtime="onnxruntime", attribution_method="gradient")
    assert PerceptionConfig(runtime="openvino", precision="bf16").precision == "bf16"


def test_the_device_picks_onnxruntimes_execution_provider(tmp_path: Path) -> None:
    from respecd.perception.runtimes.onnxruntime import CPU, CUDA, TENSORRT, providers

    assert providers("cpu", tmp_path) == [CPU]
    assert providers("cuda:1", tmp_path) == [(CUDA, {"device_id": "1"}), CPU]
    trt = providers("tensorrt", tmp_path, precision="f16")
    assert [p[0] for p in trt[:2]] == [TENSORRT, CUDA] and trt[2] == CPU
    assert trt[0][1]["trt_fp16_enable"] == "True" and trt[0][1]["trt_engine_cache_path"] == str(tmp_path / "tensorrt")
    assert providers("tensorrt:0", tmp_path, crops=True) == [(CUDA, {"device_id": "0"}), CPU]  # no engine per crop
    for bad in ("gpu", "cuda:x", "cpu:0", "tensorrt:"):
        with pytest.raises(ConfigError, match="not a device of runtime onnxruntime"):
            providers(bad, tmp_path)


def test_openvino_device_names() -> None:
    from respecd.perception.runtimes.openvino import parse_device

    assert (parse_device("cpu"), parse_device("gpu"), parse_device("gpu:1")) == ("CPU", "GPU", "GPU.1")
    with pytest.raises(ConfigError, match="not a device of runtime openvino"):
        parse_device("cuda")


@pytest.mark.parametrize(("runtime", "extra"), [("onnxruntime", "onnx"), ("openvino", "openvino")])
def test_a_runtime_that_is_not_installed_is_one_line_and_exports_nothing(
    runtime: str, extra: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from respecd.perception.detector import FusionDetector

    monkeypatch.setitem(sys.modules, runtime, None)  # as if absent: importing it raises ImportError
    config = PerceptionConfig(runtime=runtime)
    with pytest.raises(ConfigError, match=rf"perception.runtime: .*{runtime}.*pip install 'respecd\[{extra}\]'"):
        FusionDetector.load(config, exports=tmp_path / "exported")
    assert not (tmp_path / "exported").exists()


def test_the_export_needs_the_onnx_package(monkeypatch: pytest.MonkeyPatch) -> None:
    from respecd.perception import runtimes

    monkeypatch.setitem(sys.modules, "onnx", None)
    assert "needs the onnx package" in str(runtimes.problem(PerceptionConfig(runtime="onnxruntime")))
    assert runtimes.problem(PerceptionConfig()) is None  # torch needs neither


def test_check_config_names_the_runtime_line_a_machine_cannot_run(tmp_path: Path, capsys) -> None:
    body = yaml.safe_load((CONFIGS / "sim-rover.yaml").read_text())
    body["perception"] = {"runtime": "onnxruntime", "device": "tensorrt:0"}
    profile = tmp_path / "p.yaml"
    profile.write_text(yaml.safe_dump(body, sort_keys=False))
    line = profile.read_text().splitlines().index("  runtime: onnxruntime") + 1
    assert main(["check-config", str(profile)]) == 2
    err = capsys.readouterr().err
    assert f"{profile}:{line}: perception.runtime:" in err  # no TensorRT provider here (or no onnxruntime at all)


@needs_onnx
@pytest.mark.slow
def test_the_export_is_cached_by_checkpoint_and_redone_when_damaged(tmp_path: Path) -> None:
    from respecd.perception import checkpoint, export

    path = checkpoint.resolve("builtin:rgbt-hituav")
    model, _ = checkpoint.load("builtin:rgbt-hituav")
    folder = export.cached(model, path, tmp_path, "builtin:rgbt-hituav")
    manifest = export.read_manifest(folder, model.spec)
    assert folder.name.startswith(f"rgbt-hituav-{export.checkpoint_hash(path)[:16]}-")
    assert set(manifest["graphs"]) == {"rgb", "aux", "fuse"} and manifest["sha256"] == export.checkpoint_hash(path)
    stamp = (folder / "fuse.onnx").stat().st_mtime_ns
    assert export.cached(model, path, tmp_path) == folder and (folder / "fuse.onnx").stat().st_mtime_ns == stamp
    (folder / "aux.onnx").unlink()  # damaged: exported again
    assert export.cached(model, path, tmp_path) == folder and (folder / "aux.onnx").is_file()
    assert [p.name for p in tmp_path.iterdir()] == [folder.name]  # no temporary folder left behind
    with pytest.raises(ConfigError, match="exported from another net"):
        export.read_manifest(folder, checkpoint.spec_of("builtin:sim-rover"))


@needs_onnx
@pytest.mark.slow
def test_respecd_export_writes_every_part_and_the_manifest(tmp_path: Path, capsys) -> None:
    out = tmp_path / "onnx"
    assert main(["export", "builtin:rgbt-hituav", "--to", "onnx", str(out)]) == 0
    printed = capsys.readouterr().out
    assert {p.name for p in out.iterdir()} == {"rgb.onnx", "aux.onnx", "fuse.onnx", "manifest.json"}
    assert "sha256" in printed
    if installed("onnxruntime"):  # each graph checked against torch on the example input
        worst = [float(line.rsplit("= ", 1)[1]) for line in printed.splitlines() if "max |onnxruntime" in line]
        assert len(worst) == 3 and max(worst) < 1e-3


def test_respecd_export_of_a_missing_checkpoint_is_exit_2(tmp_path: Path, capsys) -> None:
    assert main(["export", str(tmp_path / "none.pt"), "--to", "onnx", str(tmp_path / "out")]) == 2
    assert "no such checkpoint file" in capsys.readouterr().err
