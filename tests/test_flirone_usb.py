"""The pyusb transport of the FLIR One driver, run through the real pyusb library on a pyusb
backend that plays the camera (pyusb's own backend seam, below usb.core): the start and stop
sequences on the wire, EP 0x85 reads of the recorded Gen-3 capture, and USB error mapping."""

from __future__ import annotations

import array
import asyncio
import errno
from pathlib import Path
from types import SimpleNamespace

import pytest
import usb.backend
import usb.core

from respecd.clock import MonotonicClock
from respecd.drivers.flirone import FlirOneConfig, FlirOneDriver
from respecd.drivers.flirone_protocol import FrameAssembler
from respecd.drivers.flirone_usb import FILEIO_HANDSHAKE, PyUsbTransport, RecordedTransport
from respecd.errors import DriverIOError, DriverUnavailableError

# Interfaces and endpoints as the reference drivers use them (flirone-v4l2, SENSORS.md §3):
# 0 status (EP 0x81 in), 1 FileIO (EP 0x02 out, 0x83 in), 2 frames (EP 0x85 in); configuration 3.
INTERFACES = {0: (0x81,), 1: (0x02, 0x83), 2: (0x85,)}


def _desc(**fields) -> SimpleNamespace:
    return SimpleNamespace(bLength=0, extra_descriptors=[], **fields)


class FlirBackend(usb.backend.IBackend):
    """A FLIR One (09cb:1996) that streams recorded EP 0x85 reads; records every request."""

    def __init__(self, chunks: list[bytes], fail: dict[str, list[usb.core.USBError]] | None = None) -> None:
        self.chunks = list(chunks)
        self.fail = fail or {}
        self.log: list[tuple] = []
        self.configuration = 0

    def _maybe_fail(self, what: str) -> None:
        if self.fail.get(what):
            raise self.fail[what].pop(0)

    # descriptors
    def enumerate_devices(self):
        yield "flir"

    def get_device_descriptor(self, dev):
        return _desc(bDescriptorType=1, bcdUSB=0x200, bDeviceClass=0xEF, bDeviceSubClass=2, bDeviceProtocol=1,
                     bMaxPacketSize0=64, idVendor=0x09CB, idProduct=0x1996, bcdDevice=0x100, iManufacturer=0,
                     iProduct=0, iSerialNumber=0, bNumConfigurations=1, address=5, bus=1, port_number=1,
                     port_numbers=(1,), speed=3)

    def get_configuration_descriptor(self, dev, config):
        return _desc(bDescriptorType=2, wTotalLength=0, bNumInterfaces=3, bConfigurationValue=3,
                     iConfiguration=0, bmAttributes=0x80, bMaxPower=250)

    def get_interface_descriptor(self, dev, intf, alt, config):
        if intf >= len(INTERFACES) or alt > 0:  # pyusb probes alternate settings until IndexError
            raise IndexError(intf)
        return _desc(bDescriptorType=4, bInterfaceNumber=intf, bAlternateSetting=0,
                     bNumEndpoints=len(INTERFACES[intf]), bInterfaceClass=0xFF, bInterfaceSubClass=0xF0,
                     bInterfaceProtocol=0, iInterface=0)

    def get_endpoint_descriptor(self, dev, ep, intf, alt, config):
        return _desc(bDescriptorType=5, bEndpointAddress=INTERFACES[intf][ep], bmAttributes=2,
                     wMaxPacketSize=512, bInterval=0, bRefresh=0, bSynchAddress=0)

    # requests
    def open_device(self, dev):
        return "handle"

    def close_device(self, dev_handle):
        self.log.append(("close",))

    def set_configuration(self, dev_handle, config_value):
        self._maybe_fail("set_configuration")
        self.configuration = config_value
        self.log.append(("set_configuration", config_value))

    def get_configuration(self, dev_handle):
        return self.configuration

    def claim_interface(self, dev_handle, intf):
        self.log.append(("claim", intf))

    def release_interface(self, dev_handle, intf):
        self.log.append(("release", intf))

    def is_kernel_driver_active(self, dev_handle, intf):
        return False

    def ctrl_transfer(self, dev_handle, bmRequestType, bRequest, wValue, wIndex, data, timeout):
        self.log.append(("ctrl", bmRequestType, bRequest, wValue, wIndex, bytes(data), timeout))
        return len(data)

    def bulk_write(self, dev_handle, ep, intf, data, timeout):
        self.log.append(("write", ep, bytes(data)))
        return len(data)

    def bulk_read(self, dev_handle, ep, intf, buff, timeout):
        if ep != 0x85:
            self.log.append(("poll", ep, timeout))
            raise usb.core.USBTimeoutError("Operation timed out", -7, errno.ETIMEDOUT)
        self._maybe_fail("bulk_read")
        if not self.chunks:
            raise usb.core.USBTimeoutError("Operation timed out", -7, errno.ETIMEDOUT)
        chunk = self.chunks.pop(0)
        buff[: len(chunk)] = array.array("B", chunk)
        return len(chunk)

    def clear_halt(self, dev_handle, ep):
        self.log.append(("clear_halt", ep))


@pytest.fixture
def chunks(shared_data: Path) -> list[bytes]:
    return RecordedTransport.from_path(shared_data / "flirone_pro_gen3_usb_moezemara" / "test_chunks_hex").chunks


def usb_error(code: int) -> usb.core.USBError:
    return usb.core.USBError(errno.errorcode[code], -1, code)


def test_start_sequence_and_recorded_reads(chunks: list[bytes]) -> None:
    backend = FlirBackend(chunks)
    transport = PyUsbTransport(backend=backend)
    transport.start()
    ctrl = [entry[1:] for entry in backend.log if entry[0] == "ctrl"]
    assert ("set_configuration", 3) in backend.log
    assert [e[1] for e in backend.log if e[0] == "claim"] == [0, 1, 2]
    # stop frames, stop FileIO, start FileIO (100 ms, no data), start video (wLength 2, 200 ms)
    assert ctrl == [(1, 0x0B, 0, 2, b"", 100), (1, 0x0B, 0, 1, b"", 100), (1, 0x0B, 1, 1, b"", 100),
                    (1, 0x0B, 1, 2, b"\x00\x00", 200)]
    assembler = FrameAssembler()
    frames = []
    for _ in range(len(chunks) + 2):
        frames += assembler.feed(transport.read(1 << 20, 100))
    assert len(frames) == 20 and transport.read(1 << 20, 100) == b""  # a timeout reads as no bytes
    assert ("poll", 0x81, 10) in backend.log and ("poll", 0x83, 10) in backend.log
    transport.close()
    tail = backend.log[-6:]
    assert tail[:2] == [("ctrl", 1, 0x0B, 0, 2, b"", 100), ("ctrl", 1, 0x0B, 0, 1, b"", 100)]
    assert ("release", 2) in tail and tail[-1] == ("close",)
    transport.close()  # twice is harmless


def test_fileio_handshake_precedes_video_start(chunks: list[bytes]) -> None:
    backend = FlirBackend(chunks)
    PyUsbTransport(fileio_handshake=True, backend=backend).start()
    order = [e[0] if e[0] != "ctrl" else f"ctrl{e[3]}{e[4]}" for e in backend.log if e[0] in ("ctrl", "write")]
    assert order == ["ctrl02", "ctrl01", "ctrl11", "write", "write", "write", "write", "ctrl12"]
    assert [e[2] for e in backend.log if e[0] == "write"] == list(FILEIO_HANDSHAKE)


def test_unplug_is_unavailable(chunks: list[bytes]) -> None:
    transport = PyUsbTransport(backend=FlirBackend(chunks, {"bulk_read": [usb_error(errno.ENODEV)]}))
    transport.start()
    with pytest.raises(DriverUnavailableError, match="unplugged"):
        transport.read(1 << 20, 100)


def test_io_errors_clear_halt_then_fail(chunks: list[bytes]) -> None:
    backend = FlirBackend(chunks, {"bulk_read": [usb_error(errno.EPIPE)]})
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
    backend = FlirBackend(chunks, {"set_configuration": [usb_error(errno.EACCES)]})
    with pytest.raises(DriverUnavailableError, match="permission denied: install systemd/99-respecd.rules"):
        PyUsbTransport(backend=backend).start()


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
