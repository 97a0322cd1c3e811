"""The FLIR One's USB transport seam: the real pyusb device and recorded endpoint reads.

Both speak ``start()``, ``read(size, timeout_ms) -> bytes`` (``b""`` when nothing arrived in
time) and ``close()``, so the frame assembler and the driver above them run unchanged on a
camera or on a capture. All calls block; the driver makes them from its worker thread.

USB facts (SENSORS.md §3, flirone-v4l2): configuration 3, interfaces 0 (control/status),
1 (FileIO), 2 (frames); vendor control-OUT requests bmRequestType 0x01, bRequest 0x0B,
wValue 0 = stop / 1 = start, wIndex = interface, 100 ms timeout ("don't change"); the video
start carries wLength 2 and gets 200 ms. Frames arrive on bulk EP 0x85; EP 0x81 (status
JSON) and 0x83 (FileIO) are drained with 10 ms timeouts, as the reference driver does.
"""

from __future__ import annotations

import array
import errno
import time
from pathlib import Path
from typing import Any, Protocol

import structlog

from respecd.errors import DriverIOError, DriverUnavailableError

log = structlog.get_logger(__name__)

VENDOR_ID, PRODUCT_ID = 0x09CB, 0x1996
CONFIGURATION = 3
INTERFACES = (0, 1, 2)
EP_FRAMES, EP_STATUS, EP_FILEIO = 0x85, 0x81, 0x83
EP_FILEIO_OUT = 0x02
REQ_TYPE_VENDOR_OUT, REQ_START_STOP = 0x01, 0x0B
CONTROL_TIMEOUT_MS = 100  # flirone-v4l2: "don't change timeout=100ms !!"
VIDEO_START_TIMEOUT_MS = 200
SIDE_POLL_TIMEOUT_MS = 10
SIDE_POLL_PERIOD_S = 0.1  # drain 0x81/0x83 at most this often so 0x85 keeps the bandwidth
IO_ERRORS_BEFORE_FAIL = 3  # consecutive bulk errors (after clear_halt) before the driver restarts
# Gen-3 FileIO preamble (moezemara's Gen-3 driver sends it before starting video; optional)
FILEIO_HANDSHAKE = (
    b"\xcc\x01\x00\x00\x01\x00\x00\x00A\x00\x00\x00\xf8\xb3\xf7\x00",
    b'{"type":"openFile","data":{"mode":"r","path":"CameraFiles.zip"}}\x00',
    b"\xcc\x01\x00\x00\x01\x00\x00\x00\x33\x00\x00\x00\xef\xdb\xc1\xc1",
    b'{"type":"readFile","data":{"streamIdentifier":10}}\x00',
)


class Transport(Protocol):
    """The seam between the driver and the bytes of EP 0x85."""

    def start(self) -> None: ...

    def read(self, size: int, timeout_ms: int) -> bytes: ...

    def close(self) -> None: ...


class PyUsbTransport:
    """The camera through pyusb and libusb-1.0."""

    def __init__(self, read_size: int = 1 << 20, fileio_handshake: bool = False, backend: Any = None) -> None:
        self.read_size = read_size
        self.fileio_handshake = fileio_handshake
        self.backend = backend  # a pyusb backend; None: libusb-1.0
        self.recovered_errors = 0
        self._dev: Any = None
        self._usb: Any = None
        self._buf = array.array("B", bytes(read_size))
        self._failures = 0
        self._next_side_poll = 0.0

    def start(self) -> None:
        self._usb = _import_pyusb()
        backend = self.backend or self._usb.backend.libusb1.get_backend()
        if backend is None:
            raise DriverUnavailableError(
                "flirone: libusb-1.0 not found (pyusb has no backend); install it, e.g. apt install libusb-1.0-0"
            )
        dev = self._usb.core.find(idVendor=VENDOR_ID, idProduct=PRODUCT_ID, backend=backend)
        if dev is None:
            raise DriverUnavailableError("flirone: no FLIR One (09cb:1996) on the USB bus; plugged in?")
        self._dev = dev
        try:
            self._setup(dev)
        except self._usb.core.USBError as err:
            self.close()
            hint = " (permission denied: install systemd/99-respecd.rules)" if err.errno == errno.EACCES else ""
            raise DriverUnavailableError(f"flirone: USB setup failed: {err}{hint}") from err
        log.info("flirone_usb_started", fileio_handshake=self.fileio_handshake)

    def _setup(self, dev: Any) -> None:
        for interface in INTERFACES:
            try:
                if dev.is_kernel_driver_active(interface):
                    dev.detach_kernel_driver(interface)
            except (NotImplementedError, self._usb.core.USBError):
                pass  # no kernel driver binds this vendor-class device on most systems
        dev.set_configuration(CONFIGURATION)
        for interface in INTERFACES:
            self._usb.util.claim_interface(dev, interface)
        self._control(0, 2)  # stop frames
        self._control(0, 1)  # stop FileIO
        self._control(1, 1)  # start FileIO
        if self.fileio_handshake:
            for message in FILEIO_HANDSHAKE:
                dev.write(EP_FILEIO_OUT, message, 500)
        self._control(1, 2, b"\x00\x00", VIDEO_START_TIMEOUT_MS)  # start video, wLength 2

    def _control(self, value: int, iface: int, data: bytes | None = None, timeout: int = CONTROL_TIMEOUT_MS) -> None:
        self._dev.ctrl_transfer(REQ_TYPE_VENDOR_OUT, REQ_START_STOP, value, iface, data, timeout)

    def read(self, size: int, timeout_ms: int) -> bytes:
        usb = self._usb
        self._poll_side_endpoints()
        if len(self._buf) != size:  # pyusb fills an array.array in place (a memoryview is refused)
            self._buf = array.array("B", bytes(size))
        try:
            count = self._dev.read(EP_FRAMES, self._buf, timeout_ms)
        except usb.core.USBTimeoutError:
            return b""
        except usb.core.USBError as err:
            self._bulk_error(err)
            return b""
        self._failures = 0
        return self._buf[:count].tobytes()

    def _bulk_error(self, err: Any) -> None:
        if err.errno == errno.ENODEV:
            raise DriverUnavailableError("flirone: camera unplugged (USB no device)") from err
        self._failures += 1
        self.recovered_errors += 1
        log.warning("flirone_bulk_error", error=str(err), consecutive=self._failures)
        if self._failures >= IO_ERRORS_BEFORE_FAIL:
            raise DriverIOError(f"flirone: {self._failures} bulk read errors in a row: {err}") from err
        try:
            self._dev.clear_halt(EP_FRAMES)  # a stalled endpoint recovers this way
        except self._usb.core.USBError:
            pass

    def _poll_side_endpoints(self) -> None:
        now = time.monotonic()
        if now < self._next_side_poll:
            return
        self._next_side_poll = now + SIDE_POLL_PERIOD_S
        for endpoint in (EP_STATUS, EP_FILEIO):
            try:
                data = self._dev.read(endpoint, 4096, SIDE_POLL_TIMEOUT_MS)
            except self._usb.core.USBTimeoutError:
                continue
            except self._usb.core.USBError as err:
                if err.errno == errno.ENODEV:  # flirone-v4l2: NO_DEVICE on 0x83 -> restart
                    raise DriverUnavailableError("flirone: camera unplugged (USB no device)") from err
                continue
            if endpoint == EP_STATUS and len(data):
                log.debug("flirone_status", text=bytes(data).rstrip(b"\x00").decode("ascii", "replace")[:200])

    def close(self) -> None:
        dev, self._dev = self._dev, None
        if dev is None:
            return
        usb = self._usb
        for value, interface in ((0, 2), (0, 1)):  # stop video, stop FileIO: leave it restartable
            try:
                dev.ctrl_transfer(REQ_TYPE_VENDOR_OUT, REQ_START_STOP, value, interface, None, CONTROL_TIMEOUT_MS)
            except usb.core.USBError:
                pass
        for interface in INTERFACES:
            try:
                usb.util.release_interface(dev, interface)
            except usb.core.USBError:
                pass
        usb.util.dispose_resources(dev)


def _import_pyusb() -> Any:
    try:
        import usb.backend.libusb1
        import usb.core
        import usb.util
    except ImportError as err:
        raise DriverUnavailableError("flirone: pyusb is not installed (pip install pyusb)") from err
    return usb


class RecordedTransport:
    """Recorded EP 0x85 reads played back through the same seam (tests, demos, CI).

    ``pace_hz`` spaces frame starts in wall time like the camera (None: as fast as read).
    """

    def __init__(self, chunks: list[bytes], loop: bool = False, pace_hz: float | None = None) -> None:
        self.chunks = [c for c in chunks if c]
        self.loop = loop
        self.pace_hz = pace_hz
        self.position = 0
        self.passes = 0
        self._rest = b""
        self._next_frame_at = 0.0

    @classmethod
    def from_path(cls, path: str | Path, **kwargs: Any) -> RecordedTransport:
        """A folder of hex files named 1.txt, 2.txt, ... (one bulk read each) or a raw byte file."""
        path = Path(path)
        if path.is_dir():
            files = sorted((p for p in path.glob("*.txt") if p.stem.isdigit()), key=lambda p: int(p.stem))
            chunks = [bytes.fromhex(p.read_text().strip()) for p in files]
        else:
            data = path.read_bytes()
            chunks = [data[i : i + 32768] for i in range(0, len(data), 32768)]  # the Gen-3 read size
        if not chunks:
            raise DriverUnavailableError(f"flirone: no recorded reads in {path}")
        return cls(chunks, **kwargs)

    @property
    def exhausted(self) -> bool:
        return not self.loop and not self._rest and self.position >= len(self.chunks)

    def start(self) -> None:
        self._next_frame_at = time.monotonic()

    def read(self, size: int, timeout_ms: int) -> bytes:
        if not self._rest:
            if self.position >= len(self.chunks):
                if not self.loop or not self.chunks:
                    return b""
                self.position = 0
                self.passes += 1
            self._rest = self.chunks[self.position]
            self.position += 1
            self._pace(self._rest)
        out, self._rest = self._rest[:size], self._rest[size:]
        return out

    def _pace(self, chunk: bytes) -> None:
        if self.pace_hz is None or not chunk.startswith(b"\xef\xbe\x00\x00"):
            return
        delay = self._next_frame_at - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        self._next_frame_at = max(self._next_frame_at, time.monotonic() - 1.0) + 1.0 / self.pace_hz

    def close(self) -> None:
        self._rest = b""
