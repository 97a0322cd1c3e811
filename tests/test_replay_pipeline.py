"""End to end through the CLI: a short simulated session replayed with ``--replay --speed max``
(deterministic), under several policies into one report, from a cut file, and refused with
exit 2 for missing, empty or non-MCAP input. The replayed session is recorded in lockstep
(``record_simulated``: the same frames however loaded the machine; live, a starved renderer
left a single RGB frame in 4 s); one recorded live through ``respecd --record`` is read with
the MCAP reader and its state directory replayed from."""

from __future__ import annotations

import json
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import structlog
import yaml
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory

from respecd.cli import main

CONFIGS = Path(__file__).resolve().parents[1] / "configs"


@pytest.fixture(autouse=True)
def _fresh_logging() -> Iterator[None]:
    """``respecd`` configures structlog onto this test's captured stdout; undo it after."""
    yield
    structlog.reset_defaults()


def _test_profile(root: Path) -> Path:
    """The simulated rover at 640x360 without depth or detector, several scenes and a dozen
    chunks in 4 s; written to ``root/profile.yaml``."""
    profile = yaml.safe_load((CONFIGS / "sim-rover.yaml").read_text())
    profile["name"] = "sim-rover-test"
    profile["sensors"] = [s for s in profile["sensors"] if s["name"] != "depth"]  # keep the test light
    profile["sensors"][0]["resolution"] = [640, 360]
    profile["perception"] = {"enabled": False}  # no trained weights in the test environment
    profile["simulation"]["scenario_duration_s"] = 1.5  # several scenes within the session
    profile["controller"] = {"decision_period_s": 0.5, "window_s": 0.5}
    profile["recording"] = {**profile["recording"], "chunk_size_kib": 256}  # a dozen chunks
    config = root / "profile.yaml"
    config.write_text(yaml.safe_dump(profile))
    return config


@pytest.fixture(scope="module")
def session_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """4 s of the simulated rover, recorded in lockstep: the same log on a loaded machine."""
    from respecd.config import load_profile
    from respecd.record.simulated import record_simulated

    root = tmp_path_factory.mktemp("session")
    return record_simulated(load_profile(_test_profile(root)), root / "session.mcap", seconds=4.0, seed=0)


@pytest.fixture(scope="module")
def live_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """4 s of the simulated rover recorded live (wall clock) through ``respecd --record``; how
    many frames it holds depends on the machine's load."""
    root = tmp_path_factory.mktemp("live")
    log = root / "session.mcap"
    argv = [sys.executable, "-m", "respecd.cli", "--config", str(_test_profile(root)), "--duration", "4",
            "--record", str(log), "--state-dir", str(root / "state"), "--log-level", "warning", "--log-format", "json"]
    # a live run ends its process with os._exit (SIGTERM budget), so it gets a process of its own
    done = subprocess.run(argv, capture_output=True, text=True, timeout=120, check=False)
    assert done.returncode == 0, done.stderr
    return log


@pytest.mark.slow
def test_recorded_session_opens_with_the_mcap_reader(live_log: Path) -> None:
    schemas: dict[str, set[str]] = {}
    with open(live_log, "rb") as f:
        reader = make_reader(f)
        decoders = DecoderFactory()
        for schema, channel, message in reader.iter_messages():
            schemas.setdefault(channel.topic, set()).add(schema.name)
            if schema.name.startswith("foxglove."):  # Foxglove's own protobuf types, every byte a field
                decoded = decoders.decoder_for(channel.message_encoding, schema)(message.data)
                assert channel.message_encoding == "protobuf" and decoded.SerializeToString() == message.data
            else:
                assert channel.message_encoding == "json" and isinstance(json.loads(message.data), dict)
        profile = {m.name: m.metadata for m in reader.iter_metadata()}["respecd.profile"]
    assert json.loads(profile["json"])["name"] == "sim-rover-test"
    assert schemas["/sensors/rgb"] == {"foxglove.CompressedImage"}
    assert schemas["/sensors/thermal"] == {"foxglove.CompressedImage"}  # lossless 16-bit PNG
    assert schemas["/sensors/radar"] == {"foxglove.PointCloud"}
    assert schemas["/sensors/thermal/colormap"] == {"foxglove.CompressedImage"}
    assert schemas["/tf"] == {"foxglove.FrameTransforms"}
    assert schemas["/sensors/rgb/calibration"] == {"foxglove.CameraCalibration"}
    assert {"/respecd/decision", "/respecd/sync", "/respecd/config"} <= set(schemas)


def _replay(log: Path, report: Path, *extra: str) -> int:
    return main(["--replay", str(log), "--speed", "max", "--report", str(report), "--log-level", "warning",
                 "--log-format", "json", *extra])


@pytest.mark.slow
def test_speed_max_replays_are_identical(session_log: Path, tmp_path: Path) -> None:
    assert _replay(session_log, tmp_path / "a.json", "--seed", "3") == 0
    assert _replay(session_log, tmp_path / "b.json", "--seed", "3") == 0
    a = json.loads((tmp_path / "a.json").read_text())["policies"]["learn"]
    b = json.loads((tmp_path / "b.json").read_text())["policies"]["learn"]
    assert len(a["decisions"]) >= 5
    assert a["decisions"] == b["decisions"]
    assert a["configs"] == b["configs"] and a["compute"]["frames"] == b["compute"]["frames"]
    assert {"t", "state", "action", "reward"} <= set(a["decisions"][0])
    assert (tmp_path / "a.png").stat().st_size > 10_000


@pytest.mark.slow
def test_speed_max_with_the_detector_is_deterministic(session_log: Path, tmp_path: Path) -> None:
    """The detector runs in its own worker thread: lockstep must not let its timing leak."""
    from respecd.errors import ConfigError
    from respecd.perception.checkpoint import resolve

    try:
        resolve("builtin:sim-rover")
    except ConfigError:
        pytest.skip("no built-in detector checkpoint (run `make weights`)")
    profile = yaml.safe_load((session_log.parent / "profile.yaml").read_text())
    profile["perception"] = {"enabled": True}
    config = tmp_path / "with-detector.yaml"
    config.write_text(yaml.safe_dump(profile))
    extra = ("--config", str(config), "--duration", "1.5", "--seed", "5")
    assert _replay(session_log, tmp_path / "a.json", *extra) == 0
    assert _replay(session_log, tmp_path / "b.json", *extra) == 0
    a = json.loads((tmp_path / "a.json").read_text())["policies"]["learn"]
    b = json.loads((tmp_path / "b.json").read_text())["policies"]["learn"]
    assert a["compute"]["percepts"] >= 5 and a["latency_model"].startswith("default")
    assert a["timeline"] == b["timeline"]  # same detections, same modelled latencies
    assert a["decisions"] == b["decisions"] and len(a["decisions"]) >= 2


def _with_detector(session_log: Path, tmp_path: Path, **perception: Any) -> Path:
    """The session's profile with the shipped detector on (skips without the checkpoint)."""
    from respecd.errors import ConfigError
    from respecd.perception.checkpoint import resolve

    try:
        resolve("builtin:sim-rover")
    except ConfigError:
        pytest.skip("no built-in detector checkpoint (run `make weights`)")
    profile = yaml.safe_load((session_log.parent / "profile.yaml").read_text())
    profile["perception"] = {"enabled": True, **perception}
    config = tmp_path / "with-detector.yaml"
    config.write_text(yaml.safe_dump(profile))
    return config


def _join_perception_threads() -> None:
    """An inference still running when a replay ends finishes on its own (seconds, under load)."""
    for thread in threading.enumerate():
        if thread.name.startswith("perception"):
            thread.join(timeout=60)
            assert not thread.is_alive()


@pytest.mark.slow
def test_a_replay_decodes_only_the_rgb_frames_the_detector_runs_on(
    session_log: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A frame superseded before the detector takes a bundle is never decoded, ahead or not."""
    from respecd.record import legacy
    from respecd.replay.run import replay

    config = _with_detector(session_log, tmp_path)
    decoded: list[int] = []
    real = legacy.decode_compressed
    def counted(raw: bytes, fmt: str) -> Any:
        if fmt == "jpeg":  # the RGB frames (thermal and depth are PNG)
            decoded.append(len(raw))
        return real(raw, fmt)

    monkeypatch.setattr(legacy, "decode_compressed", counted)
    entry = replay(session_log, config=config, policy="static", duration=2.0)["policies"]["static"]
    served, percepts = entry["compute"]["frames"]["rgb"], entry["compute"]["percepts"]
    assert served > percepts >= 3  # the detector (paced by its modelled latency) skips frames
    # the detector's frames, plus the first frame (the replay reads the logged size from it) and
    # the frame of an inference still running (or decoded ahead for one) when the replay ends,
    # whose percept is never counted
    assert len(decoded) <= percepts + 2 < served + 2
    _join_perception_threads()


@pytest.mark.slow
def test_a_replay_prepares_the_next_bundle_while_the_detector_runs(
    session_log: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The inputs prepared ahead are those of the detector's next bundles; the detector runs on
    them as they were prepared, and they are bit for bit what it would have prepared itself."""
    from respecd.perception.detector import FusionDetector
    from respecd.replay.run import replay

    config = _with_detector(session_log, tmp_path)
    ahead: dict[int, dict[str, tuple[int, float]]] = {}  # id of each input prepared ahead -> its frames
    ran: list[tuple[dict[str, tuple[int, float]], Any]] = []  # (the frames run on, the input given or None)
    mismatched: list[dict[str, tuple[int, float]]] = []
    real_prepare, real_infer = FusionDetector.prepare, FusionDetector.infer

    def which(frames: dict[str, Any]) -> dict[str, tuple[int, float]]:
        return {m: (f.seq, f.t) for m, f in frames.items() if m in ("rgb", "thermal", "radar")}

    def prepare(self: FusionDetector, frames: dict[str, Any], rgb_size: Any = None) -> Any:
        aligned = real_prepare(self, frames, rgb_size)
        if threading.current_thread().name.startswith("perception-prepare"):
            ahead[id(aligned)] = which(frames)
        return aligned

    def infer(self: FusionDetector, frames: dict[str, Any], attribute: bool, aligned: Any = None,
              rgb_size: Any = None) -> Any:
        ran.append((which(frames), aligned))
        if aligned is not None:
            here = real_prepare(self, frames, rgb_size)  # the grid the stage gives a bundle without RGB
            same = (here.size == aligned.size and here.tensor.dtype == aligned.tensor.dtype
                    and here.tensor.shape == aligned.tensor.shape and here.tensor.tobytes() == aligned.tensor.tobytes()
                    and here.presence.tobytes() == aligned.presence.tobytes())
            if not same:
                mismatched.append(which(frames))
        return real_infer(self, frames, attribute, aligned, rgb_size)

    monkeypatch.setattr(FusionDetector, "prepare", prepare)
    monkeypatch.setattr(FusionDetector, "infer", infer)
    replay(session_log, config=config, policy="static", duration=2.0)
    _join_perception_threads()
    run_on = [frames for frames, _ in ran]
    assert len(run_on) >= 4 and ran[0][1] is None  # nothing is ahead of the first bundle
    # each input prepared ahead is a later inference's (but the last: its bundle's inference may be cut
    # off by the replay's end), never the first inference's, each once
    assert sum(frames not in run_on[1:] for frames in ahead.values()) <= 1
    assert len({str(frames) for frames in ahead.values()}) == len(ahead) >= (len(run_on) - 1) // 2
    used = [(frames, aligned) for frames, aligned in ran if aligned is not None]
    assert len(used) >= (len(ran) - 1) // 2  # the detector found its input prepared
    assert all(ahead.get(id(aligned)) == frames for frames, aligned in used)  # for those very frames
    assert mismatched == []


@pytest.mark.slow
def test_nothing_is_prepared_ahead_when_the_detector_takes_every_core(
    session_log: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Preparing ahead would take a core from the detector's threads: the detector prepares itself."""
    import os

    from respecd.perception.detector import FusionDetector
    from respecd.replay.run import replay

    config = _with_detector(session_log, tmp_path, torch_threads=len(os.sched_getaffinity(0)))
    threads: list[str] = []
    real_prepare = FusionDetector.prepare
    def prepare(self: FusionDetector, frames: dict[str, Any], rgb_size: Any = None) -> Any:
        threads.append(threading.current_thread().name)
        return real_prepare(self, frames, rgb_size)

    monkeypatch.setattr(FusionDetector, "prepare", prepare)
    entry = replay(session_log, config=config, policy="static", duration=1.0)["policies"]["static"]
    _join_perception_threads()
    assert entry["compute"]["percepts"] >= 2 and len(threads) >= 2
    assert all(name.startswith("perception_") for name in threads)  # the detector's own thread


def _with_cut_images(log: Path, out: Path, topic: str) -> Path:
    """``log`` with each JPEG on ``topic`` but the first cut after its header (its size still
    reads, its pixels do not decode), every other record as it was."""
    from mcap.writer import Writer

    with open(log, "rb") as src, open(out, "wb") as dst:
        reader, writer = make_reader(src), Writer(dst)
        writer.start()
        schemas: dict[int, int] = {}
        channels: dict[int, int] = {}
        seen = 0
        for schema, channel, message in reader.iter_messages():
            if schema is not None and schema.id not in schemas:
                schemas[schema.id] = writer.register_schema(schema.name, schema.encoding, schema.data)
            if channel.id not in channels:
                channels[channel.id] = writer.register_channel(channel.topic, channel.message_encoding,
                                                               schemas.get(channel.schema_id, 0), channel.metadata)
            data = message.data
            seen += channel.topic == topic
            if channel.topic == topic and seen > 1:
                image = DecoderFactory().decoder_for(channel.message_encoding, schema)(data)
                image.data = image.data[: image.data.find(b"\xff\xda")] + b"\xff\xd9"  # up to the scan, then EOI
                data = image.SerializeToString()
            writer.add_message(channels[channel.id], message.log_time, data, message.publish_time)
        for record in reader.iter_metadata():
            writer.add_metadata(record.name, record.metadata)
        writer.finish()
    return out


@pytest.mark.slow
def test_undecodable_images_are_left_out_and_the_detector_runs_on(
    session_log: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """JPEGs whose pixels do not decode fail quietly where they are decoded ahead; where the
    detector reads them they are left out, as frames that never came, and said once: the
    detector runs on the other sensors to the log's end (no stage crash and restart, which at
    --speed max lost the rest of the log's percepts)."""
    config = _with_detector(session_log, tmp_path)
    assert _replay(session_log, tmp_path / "clean.json", "--config", str(config), "--policy", "static") == 0
    bad = _with_cut_images(session_log, tmp_path / "cut-images.mcap", "/sensors/rgb")
    assert _replay(bad, tmp_path / "r.json", "--config", str(config), "--policy", "static") == 0
    _join_perception_threads()
    events = [json.loads(line) for line in capsys.readouterr().out.splitlines() if line.startswith("{")]
    assert not [e for e in events if e["event"] == "stage_crashed"]
    said = [e for e in events if e["event"] == "frame_undecodable"]
    assert said and said[0]["sensor"] == "rgb" and "rgb frame" in said[0]["error"]
    assert "undecodable jpeg image" in said[0]["error"]
    clean = json.loads((tmp_path / "clean.json").read_text())["policies"]["static"]["compute"]["percepts"]
    entry = json.loads((tmp_path / "r.json").read_text())["policies"]["static"]
    assert entry["replayed_s"] > 3.5 and entry["compute"]["percepts"] >= 0.8 * clean


@pytest.mark.slow
def test_static_and_heuristic_give_a_comparison_table(
    session_log: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    report = tmp_path / "cmp.json"
    assert _replay(session_log, report, "--policy", "static") == 0
    assert _replay(session_log, report, "--policy", "heuristic") == 0
    table = capsys.readouterr().out.strip().splitlines()
    header = max(i for i, line in enumerate(table) if line.startswith("policy") and "F1" in line and "sensor W" in line)
    rows = [line.split()[0] for line in table[header + 1 : header + 3]]
    assert rows == ["static", "heuristic"]
    policies = json.loads(report.read_text())["policies"]
    assert set(policies) == {"static", "heuristic"}
    assert policies["static"]["actions"]["switches"] == 0  # static never moves
    for entry in policies.values():
        assert entry["reference"] == "ground_truth"  # simulated frames carry meta["gt"]
        assert entry["energy"]["total_j"] > 0 and entry["compute"]["pixels_per_s"] > 0
    assert report.with_suffix(".png").is_file()


@pytest.mark.slow
def test_cut_log_replays_up_to_the_cut_with_a_warning(
    session_log: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    cut = tmp_path / "cut.mcap"
    data = session_log.read_bytes()
    cut.write_bytes(data[: len(data) // 2])
    assert _replay(cut, tmp_path / "cut.json", "--policy", "static") == 0
    err = capsys.readouterr().err
    assert "was cut short" in err and "up to the last complete chunk" in err
    entry = json.loads((tmp_path / "cut.json").read_text())["policies"]["static"]
    assert entry["truncated"] is True
    assert 0.5 < entry["replayed_s"] < 3.9


@pytest.mark.slow
def test_damaged_log_replays_with_one_warning_per_damaged_chunk(
    session_log: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with open(session_log, "rb") as f:
        chunks = sorted(make_reader(f).get_summary().chunk_indexes, key=lambda c: c.chunk_start_offset)
    assert len(chunks) >= 4
    data = bytearray(session_log.read_bytes())
    for fraction in (0.3, 0.6):  # two different chunks, neither the last
        chunk = chunks[int(len(chunks) * fraction)]
        data[chunk.chunk_start_offset + chunk.chunk_length // 2] ^= 0xFF
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(data)
    assert _replay(bad, tmp_path / "bad.json", "--policy", "static") == 0
    captured = capsys.readouterr()
    assert "Traceback" not in captured.out + captured.err
    warnings = [json.loads(line) for line in captured.out.splitlines() if '"log.damaged"' in line]
    assert len(warnings) == 2 and all(w["level"] == "warning" and "-" in w["bytes"] for w in warnings)
    entry = json.loads((tmp_path / "bad.json").read_text())["policies"]["static"]
    assert entry["replayed_s"] > 3.5  # the rest of the log was replayed


@pytest.mark.slow
def test_speed_2_replays_on_a_scaled_wall_clock(session_log: Path, tmp_path: Path) -> None:
    entries = {}
    for speed in ("max", "2"):
        report = tmp_path / f"x{speed}.json"
        argv = ["--replay", str(session_log), "--speed", speed, "--duration", "1.5", "--policy", "heuristic",
                "--report", str(report), "--log-level", "warning"]
        assert main(argv) == 0
        entries[speed] = json.loads(report.read_text())["policies"]["heuristic"]
    entry = entries["2"]
    assert entry["speed"] == "2" and entry["latency_model"] == "none (perception off)"
    # frames flowed in real (halved) time; how many depends on what a busy loop drops (under
    # load a third of lockstep's), so only that they flowed at all
    logged = entries["max"]["compute"]["frames"]["rgb"]
    assert logged > 0 and entry["compute"]["frames"]["rgb"] > 0
    assert entry["timing"]["wall_s"] >= 0.7  # 1.5 s of log at 2x: paced by the wall clock, not lockstep


@pytest.mark.parametrize(
    ("content", "message"),
    [(None, "no such file"), (b"", "empty file (0 bytes)"), (b"not a log at all\n", "not an MCAP file")],
)
def test_bad_replay_input_is_exit_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], content: bytes | None, message: str
) -> None:
    log = tmp_path / "in.mcap"
    if content is not None:
        log.write_bytes(content)
    assert main(["--replay", str(log), "--speed", "max", "--log-level", "warning"]) == 2
    err = capsys.readouterr().err
    assert message in err and str(log) in err and "Traceback" not in err


def _files(directory: Path) -> dict[str, str]:
    import hashlib

    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(directory.iterdir())}


@pytest.mark.e2e
def test_replay_reads_but_never_changes_a_live_state_directory(live_log: Path, tmp_path: Path) -> None:
    state = live_log.parent / "state"
    before = _files(state)
    assert any(name.startswith("qtable-") for name in before)  # the live run saved its table
    assert _replay(live_log, tmp_path / "a.json", "--state-dir", str(state)) == 0
    assert _files(state) == before  # not renamed aside, not overwritten, nothing added
    saved = tmp_path / "learned.npz"
    assert _replay(live_log, tmp_path / "b.json", "--state-dir", str(state), "--save-table", str(saved)) == 0
    assert _files(state) == before
    from respecd.control.persist import read_table

    meta, _, _ = read_table(saved)
    assert meta["updates"] > 0  # --save-table is where the replay's learning goes


def _signalled_replay(argv: list[str], wait_for: str, after_s: float) -> tuple[int, str, float]:
    """Run ``respecd`` ARGV, SIGTERM it ``after_s`` after it logged ``wait_for``; (rc, stderr, stop time)."""
    import os
    import signal
    import time

    argv = [sys.executable, "-m", "respecd.cli", *argv, "--log-format", "json"]
    with subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                          env={**os.environ, "PYTHONUNBUFFERED": "1"}) as proc:
        try:
            assert proc.stdout is not None
            for line in proc.stdout:
                if f'"event": "{wait_for}"' in line:
                    break
            time.sleep(after_s)
            sent = time.monotonic()
            proc.send_signal(signal.SIGTERM)
            _, err = proc.communicate(timeout=10)
            elapsed = time.monotonic() - sent
        finally:
            if proc.poll() is None:
                proc.kill()
    return proc.returncode, err, elapsed


@pytest.mark.e2e
def test_sigterm_stops_a_replay_with_its_report(session_log: Path, tmp_path: Path) -> None:
    report = tmp_path / "r.json"
    rc, err, elapsed = _signalled_replay(["--replay", str(session_log), "--speed", "1", "--report", str(report)],
                                         "pipeline_up", 1.0)
    assert rc == 0, err[-2000:]
    assert elapsed <= 2.0, f"took {elapsed:.2f} s to stop"
    entry = json.loads(report.read_text())["policies"]["learn"]
    assert entry["stopped_early"] and 0.5 < entry["replayed_s"] < 3.5
    assert entry["decisions"]  # what was replayed before the signal is in the report


@pytest.mark.e2e
def test_sigterm_while_the_detector_loads_stops_a_lockstep_replay(session_log: Path, tmp_path: Path) -> None:
    from respecd.errors import ConfigError
    from respecd.perception.checkpoint import resolve

    try:
        resolve("builtin:sim-rover")
    except ConfigError:
        pytest.skip("no built-in detector checkpoint (run `make weights`)")
    profile = yaml.safe_load((session_log.parent / "profile.yaml").read_text())
    profile["perception"] = {"enabled": True}
    config = tmp_path / "with-detector.yaml"
    config.write_text(yaml.safe_dump(profile))
    report = tmp_path / "r.json"
    argv = ["--replay", str(session_log), "--speed", "max", "--config", str(config), "--report", str(report)]
    rc, err, elapsed = _signalled_replay(argv, "detector_loading", 0.0)
    assert rc == 0, err[-2000:]
    assert elapsed <= 2.0, f"took {elapsed:.2f} s to stop"
    entry = json.loads(report.read_text())["policies"]["learn"]
    assert entry["stopped_early"] and entry["replayed_s"] == 0.0
