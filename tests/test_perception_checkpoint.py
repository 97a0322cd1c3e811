"""Checkpoints: round trip, and a clear one-line error for every kind of bad file."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import run_cli

from respecd.errors import ConfigError
from respecd.perception import checkpoint
from respecd.perception.config import ModelSpec, PerceptionConfig
from respecd.perception.detector import FusionDetector
from respecd.perception.model import FusionNet

TINY = ModelSpec(rgb_widths=(8, 8, 16, 16, 16), aux_widths=(8, 8, 8, 8, 8), neck_widths=(16, 16, 16))


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def test_round_trip_gives_identical_outputs(tmp_path: Path) -> None:
    torch.manual_seed(0)
    model = FusionNet(TINY).eval()
    path = tmp_path / "tiny.pt"
    checkpoint.save(path, model, {"data": "unit-test"})
    card = checkpoint.write_card(path, model, {"name": "tiny"})
    loaded, payload = checkpoint.load(str(path), expected=TINY)
    x = torch.rand(1, 5, 64, 96)
    with torch.inference_mode():
        for a, b in zip(model(x), loaded(x), strict=True):
            assert torch.equal(a, b)
    assert payload["data"] == "unit-test"
    assert '"channels": [\n    "r"' in card.read_text()
    detector = FusionDetector.load(PerceptionConfig(weights=str(path), model=TINY))
    assert detector.channels == ("r", "g", "b", "thermal", "radar")


def test_garbage_file_is_a_clear_config_error(tmp_path: Path) -> None:
    path = tmp_path / "broken.pt"
    path.write_bytes(b"this is not a checkpoint")
    with pytest.raises(ConfigError, match=r"broken\.pt: not a torch checkpoint: it looks like text"):
        checkpoint.load(str(path))


def _npz(path: Path) -> None:
    with path.open("wb") as f:
        np.savez(f, q=np.zeros((3, 2)), visits=np.zeros((3, 2)))


@pytest.mark.parametrize(("name", "write", "looks_like"), [
    ("random.pt", lambda p: p.write_bytes(np.random.default_rng(1).bytes(20_000)), "unrecognised binary data"),
    ("profile.yaml", lambda p: p.write_text("name: rover\nsensors: []\n"), "text"),
    ("session.mcap", lambda p: p.write_bytes(b"\x89MCAP0\r\n" + bytes(200)), "an MCAP file"),
    ("model.onnx", lambda p: p.write_bytes(b"\x08\x06\x12\x07pytorch\x1a\x031.1" + bytes(100)), "an ONNX model"),
    ("qtable.npz", _npz, "a NumPy .npz archive"),
])
def test_a_file_that_is_no_torch_file_is_not_called_one_of_python_objects(tmp_path: Path, name: str, write,
                                                                           looks_like: str) -> None:
    path = tmp_path / name
    write(path)
    with pytest.raises(ConfigError) as info:
        checkpoint.load(str(path))
    message = str(info.value)
    assert message.startswith(f"{path}: not a torch checkpoint: it looks like {looks_like}")
    assert "expected a respecd checkpoint written by `respecd train` (a torch zip archive)" in message
    for wrong in ("Python objects", "enforce fail", "inline_container", "re-export"):
        assert wrong not in message, message


def test_a_directory_and_an_empty_file_say_so(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=f"{tmp_path}: is a directory, expected a respecd checkpoint"):
        checkpoint.load(str(tmp_path))
    (tmp_path / "empty.pt").write_bytes(b"")
    with pytest.raises(ConfigError, match=r"empty\.pt: empty file \(0 bytes\), expected a respecd checkpoint"):
        checkpoint.load(str(tmp_path / "empty.pt"))


def test_a_truncated_real_checkpoint_is_called_truncated(tmp_path: Path) -> None:
    good = tmp_path / "good.pt"
    checkpoint.save(good, FusionNet(TINY))
    cut = tmp_path / "cut.pt"
    cut.write_bytes(good.read_bytes()[:5000])
    with pytest.raises(ConfigError, match=r"cut\.pt: not a loadable torch checkpoint \(damaged or truncated"):
        checkpoint.load(str(cut))


def test_eval_with_weights_that_are_no_checkpoint_exits_2(tmp_path: Path) -> None:
    path = tmp_path / "garbage.pt"
    path.write_bytes(np.random.default_rng(2).bytes(20_000))
    result = run_cli("eval", "--data", "sim", "--weights", str(path), "--out", str(tmp_path / "ev"))
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert f"respecd: {path}: not a torch checkpoint" in result.stderr and "Python objects" not in result.stderr


def test_foreign_torch_file_is_rejected(tmp_path: Path) -> None:
    path = tmp_path / "foreign.pt"
    torch.save({"model": {"w": torch.zeros(2)}}, path)
    with pytest.raises(ConfigError, match=r"foreign\.pt: not a respecd fusion checkpoint"):
        checkpoint.load(str(path))


def test_pickled_code_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "code.pt"
    torch.save({"format": checkpoint.FORMAT, "payload": Path("/")}, path)  # arbitrary object: needs full pickle
    with pytest.raises(ConfigError, match="not a loadable torch checkpoint"):
        checkpoint.load(str(path))


def test_a_corrupt_checkpoint_never_suggests_loading_it_as_code(tmp_path: Path) -> None:
    good = tmp_path / "good.pt"
    torch.save({"format": checkpoint.FORMAT, "payload": Path("/")}, good)
    data = good.read_bytes()
    flipped = bytearray(data)
    flipped[len(data) // 3] ^= 0xFF
    for name, content in {"object.pt": data, "cut.pt": data[: len(data) // 2], "flipped.pt": bytes(flipped)}.items():
        path = tmp_path / name
        path.write_bytes(content)
        with pytest.raises(ConfigError) as info:
            checkpoint.load(str(path))
        message = str(info.value)
        assert f"{name}: not a loadable torch checkpoint (" in message
        for advice in ("weights_only", "safe_globals", "trust", "\x1b"):
            assert advice not in message, (name, message)
    assert "PosixPath" in str(pytest.raises(ConfigError, checkpoint.load, str(good)).value)  # says what it holds


def test_mismatched_spec_names_the_field(tmp_path: Path) -> None:
    path = tmp_path / "tiny.pt"
    checkpoint.save(path, FusionNet(TINY))
    wider = TINY.model_copy(update={"neck_widths": (32, 32, 32)})
    with pytest.raises(ConfigError) as info:
        FusionDetector.load(PerceptionConfig(weights=str(path), model=wider))
    assert "perception.model.neck_widths" in str(info.value)
    assert "(32, 32, 32)" in str(info.value) and "(16, 16, 16)" in str(info.value)


def test_weights_that_do_not_fit_their_spec(tmp_path: Path) -> None:
    path = tmp_path / "tampered.pt"
    payload = {"format": checkpoint.FORMAT, "spec": TINY.model_dump(mode="json"),
               "state_dict": FusionNet(TINY.model_copy(update={"neck_widths": (24, 24, 24)})).state_dict()}
    torch.save(payload, path)
    with pytest.raises(ConfigError, match="weights do not fit the model spec"):
        checkpoint.load(str(path))


def test_missing_files() -> None:
    with pytest.raises(ConfigError, match="no such checkpoint file"):
        checkpoint.load("/nonexistent/model.pt")
    with pytest.raises(ConfigError, match="no built-in checkpoint named 'nope'"):
        checkpoint.load("builtin:nope")


def test_bench_replay_refuses_bad_weights_before_its_recording_phase(tmp_path: Path) -> None:
    import time

    path = tmp_path / "garbage.pt"
    path.write_bytes(np.random.default_rng(6).bytes(20_000))
    start = time.monotonic()
    result = run_cli("bench", "replay", "--weights", str(path), "--seconds", "1")
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert f"{path}: not a torch checkpoint" in result.stderr
    assert time.monotonic() - start < 20  # the recording phase alone took over 30 s
