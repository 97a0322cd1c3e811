"""The pyusb transport of the FLIR One driver through the real, installed pyusb, on a pyusb
backend that plays the camera with its interfaces, alternate settings and endpoints
(``fake_flirone``): SET_INTERFACE on the wire and in pyusb's view, reset of a wedged
camera, side endpoints drained after every read, EP 0x85 reads of the recorded Gen-3
capture, and USB error mapping."""

from __future__ import annotations

import asyncio
import errno
from pathlib import Path

import pytest
import usb
from fake_flirone import FlirBackend, timeout_error, usb_error
from structlog.testing import capture_logs

from respecd.clock import MonotonicClock
from respecd.drivers.flirone import FlirOneConfig, FlirOneDriver
from respecd.drivers.flirone_protocol import FrameAssembler
from respecd.drivers.flirone_usb import FILEIO_HANDSHAKE, PyUsbTransport, RecordedTransport
from respecd.errors import DriverIOError, DriverUnavailableError


@pytest.fixture
def chunks(shared_data: Path) -> list[bytes]:
    return RecordedTransport.from_path(shared_data / "flirone_pro_gen3_usb_moezemara" / "test_chunks_hex").chunks


def _frames(transport: PyUsbTransport, reads: int) -> list:
    assembler, frames = FrameAssembler(), []
    for _ in range(reads):
        frames += assembler.feed(transport.read(1 << 20, 100))
    return frames


def _wire(backend: FlirBackend) -> list[tuple[int, int]]:
    """(interface, alternate setting) of every SET_INTERFACE the camera received, in order."""
    out = []
    for entry in backend.log:
        if entry[0] == "set_interface":
            out.append((entry[1], entry[2]))
        elif entry[0] == "ctrl" and entry[1:3] == (0x01, 0x0B):
            out.append((entry[4], entry[3]))
    return out


def test_installed_pyusb_looks_endpoints_up_in_the_selected_setting() -> None:
    """Why the start requests must go through pyusb: since 1.3.0 it only finds endpoints there."""
    major, minor = (int(part) for part in usb.__version__.split(".")[:2])
    assert (major, minor) >= (1, 3)


@pytest.mark.parametrize("layout", ["alt1", "alt0", "glass"])
def test_start_sequence_streams_on_every_reported_layout(chunks: list[bytes], layout: str) -> None:
    backend = FlirBackend(chunks, layout=layout)
    transport = PyUsbTransport(backend=backend)
    transport.start()
    assert ("set_configuration", 3) in backend.log and [e[1] for e in backend.log if e[0] == "claim"] == [0, 1, 2]
    # stop frames, stop FileIO, start FileIO, start video: the references' order, as SET_INTERFACE
    assert _wire(backend) == [(2, 0), (1, 0), (1, 1), (2, 1)]
    expected = {"alt1": "pyusb", "alt0": "raw", "glass": "raw"}[layout]  # setting 1 with the endpoints, or not
    assert transport.selection[(2, 1)] == expected and transport.selection[(2, 0)] == "pyusb"
    frames = _frames(transport, len(chunks) + 2)
    assert len(frames) == 20 and transport.read(1 << 20, 100) == b""  # a timeout reads as no bytes
    transport.close()
    assert _wire(backend)[-2:] == [(2, 0), (1, 0)] and ("reset",) in backend.log[-3:]
    assert ("release", 2) in backend.log
    transport.close()  # twice is harmless


def test_raw_set_interface_on_the_alt1_layout_is_what_broke(chunks: list[bytes]) -> None:
    """The previous transport's way (raw request, pyusb left in setting 0) cannot read EP 0x85 there."""
    backend = FlirBackend(chunks, layout="alt1")
    dev = usb.core.find(idVendor=0x09CB, idProduct=0x1996, backend=backend)
    dev.set_configuration(3)
    for iface, alt in ((2, 0), (1, 0), (1, 1), (2, 1)):
        dev.ctrl_transfer(0x01, 0x0B, alt, iface, None, 100)
    with pytest.raises(ValueError, match="Invalid endpoint address 0x85"):
        dev.read(0x85, 1 << 20, 100)
    usb.util.dispose_resources(dev)


def test_side_endpoints_are_drained_after_every_frame_read(chunks: list[bytes]) -> None:
    backend = FlirBackend(chunks, status_every=2, side_capacity=2)  # 1 status message per 2 reads
    transport = PyUsbTransport(backend=backend)
    transport.start()
    with capture_logs() as logs:
        frames = _frames(transport, len(chunks) + 5)  # back to back, faster than any 100-ms poll timer
    assert len(frames) == 20 and not backend.status_queue  # a full side endpoint would have stalled frames
    reads = [i for i, e in enumerate(backend.log) if e[0] == "read"]
    for a, b in zip(reads, reads[1:], strict=False):
        polled = {e[1] for e in backend.log[a:b] if e[0] == "poll"}
        assert polled == {0x81, 0x83}
    status = [e for e in logs if e["event"] == "flirone_status"]
    assert [e["type"] for e in status if e["log_level"] == "info"] == ["batteryVoltageUpdate"]  # once per type
    transport.close()


def test_a_wedged_camera_is_reset_and_started_again(chunks: list[bytes]) -> None:
    backend = FlirBackend(chunks, wedged_until_reset=True)  # e.g. left streaming by a killed process
    transport = PyUsbTransport(backend=backend)
    with capture_logs() as logs:
        transport.start()
    assert ("reset",) in backend.log and transport.resets == 1
    assert [e["event"] for e in logs if e["log_level"] == "warning"] == ["flirone_usb_reset"]
    assert len(_frames(transport, len(chunks) + 2)) == 20
    transport.close()


def test_a_camera_that_stays_wedged_is_unavailable(chunks: list[bytes]) -> None:
    backend = FlirBackend(chunks, fail={"set_interface": [timeout_error()] * 10})
    with pytest.raises(DriverUnavailableError, match="USB setup failed"):
        PyUsbTransport(backend=backend).start()
    assert backend.log.count(("reset",)) == 2  # the retry's own, then close's


def test_fileio_handshake_precedes_video_start(chunks: list[bytes]) -> None:
    backend = FlirBackend(chunks)
    PyUsbTransport(fileio_handshake=True, backend=backend).start()
    order = [e[0] if e[0] != "set_interface" else f"si{e[1]}{e[2]}" for e in backend.log
             if e[0] in ("set_interface", "write")]
    assert order == ["si20", "si10", "si11", "write", "write", "write", "write", "si21"]
    assert [e[2] for e in backend.log if e[0] == "write"] == list(FILEIO_HANDSHAKE)


def test_unplug_is_unavailable(chunks: list[bytes]) -> None:
    transport = PyUsbTransport(backend=FlirBackend(chunks, fail={"bulk_read": [usb_error(errno.ENODEV)]}))
    transport.start()
    with pytest.raises(DriverUnavailableError, match="unplugged"):
        transport.read(1 << 20, 100)


def test_io_errors_clear_halt_then_fail(chunks: list[bytes]) -> None:
    backend = FlirBackend(chunks, fail={"bulk_read": [usb_error(errno.EPIPE)]})
    transport = PyUsbTransport(backend=backend)
    transport.start()
    assert transport.read(1 << 20, 100) == b""
    assert ("clear_halt", 0x85) in backend.log and transport.recovered_errors == 1
    assert transport.read(1 << 20, 100)  # the stream goes on
    backend.fail["bulk_read"] = [usb_error(errno.EIO)] * 3
    transport.read(1 << 20, 100)
    transport.read(1 << 20, 100)
    with pytest.raises(DriverIOError, match="3 bulk read errors in a row"):
        transport.read(1 << 20, 100)


def test_permission_denied_names_the_udev_rule(chunks: list[bytes]) -> None:
    backend = FlirBackend(chunks, fail={"set_configuration": [usb_error(errno.EACCES)]})
    with capture_logs() as logs, pytest.raises(DriverUnavailableError, match="install systemd/99-respecd.rules"):
        PyUsbTransport(backend=backend).start()
    assert not [e for e in logs if e["event"] == "flirone_usb_reset"]  # a permission problem is not a wedge


async def test_driver_over_pyusb(chunks: list[bytes]) -> None:
    transport = PyUsbTransport(backend=FlirBackend(chunks))
    driver = FlirOneDriver(FlirOneConfig(name="thermal", realtime=False), MonotonicClock(), transport=transport)
    await driver.start()
    frames = []
    try:
        async with asyncio.timeout(10):
            async for frame in driver.frames():
                frames.append(frame)
                if len(frames) == 10:
                    break
    finally:
        await driver.stop()
    assert frames[0].data.shape == (60, 80) and frames[-1].meta["layout"] == (80, 60)
    assert all(f.meta["crc_errors"] == 0 for f in frames)
