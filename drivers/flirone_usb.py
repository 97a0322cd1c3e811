"""The FLIR One's USB transport seam: the real pyusb device and recorded endpoint reads.

Both speak ``start()``, ``read(size, timeout_ms) -> bytes`` (``b""`` when nothing arrived in
time) and ``close()``, so the frame assembler and the driver above them run unchanged on a
camera or on a capture. All calls block; the driver makes them from its worker thread.

USB facts (SENSORS.md §3; flirone-v4l2, sutty5's driver, moezemara's Gen-3 driver, the ROS
flir_one_node): configuration 3, interfaces 0 (control/status, EP 0x81 in / 0x02 out),
1 (FileIO, 0x83 / 0x04), 2 (frames, 0x85 / 0x06). The "start/stop" requests every
reference sends (bmRequestType 0x01, bRequest 0x0B, wValue 0/1, wIndex = interface) are the
standard USB SET_INTERFACE: alternate setting 0 = stop, 1 = start. They go through pyusb's
``set_interface_altsetting`` whenever the device describes that alternate setting, so that
pyusb (which since 1.3.0 looks endpoints up in the setting it selected) and the kernel
agree with the camera; a raw control transfer is the fallback only for a setting the
descriptors do not list, or one that would hide the endpoint read on that interface.
Frames arrive on bulk EP 0x85; EP 0x81 (status) and 0x83 (FileIO) are drained after every
frame read, as every reference does (a full side endpoint stalls the camera). ``close``
stops both streams, releases the interfaces and resets the device, as the references do, so
that the next start finds it in its power-on state; a start that fails on a wedged camera
resets it and tries once more.
"""

from __future__ import annotations

import array
import errno
import json
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
READ_ENDPOINT = {1: EP_FILEIO, 2: EP_FRAMES}  # what each streaming interface is read on
REQ_TYPE_SET_INTERFACE, REQ_SET_INTERFACE = 0x01, 0x0B  # standard, host-to-device, recipient interface
CONTROL_TIMEOUT_MS = 100  # flirone-v4l2: "don't change timeout=100ms !!"
VIDEO_START_TIMEOUT_MS = 200
SIDE_READ_TIMEOUT_MS = 10  # flirone-v4l2 and the Android drivers: 10 ms per side endpoint per loop
SIDE_READ_SIZE = 16384
SIDE_READS_MAX = 4  # per endpoint per frame read, while data keeps coming
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

    def __init__(
        self, read_size: int = 1 << 20, fileio_handshake: bool = False, backend: Any = None,
        side_timeout_ms: int = SIDE_READ_TIMEOUT_MS,
    ) -> None:
        self.read_size = read_size
        self.fileio_handshake = fileio_handshake
        self.backend = backend  # a pyusb backend; None: libusb-1.0
        self.side_timeout_ms = side_timeout_ms
        self.recovered_errors = 0
        self.resets = 0
        self.selection: dict[tuple[int, int], str] = {}  # (interface, alt) -> "pyusb" | "raw", for the log
        self.status_types: set[str] = set()  # "type" of the JSON messages seen on EP 0x81
        self._dev: Any = None
        self._usb: Any = None
        self._buf = array.array("B", bytes(read_size))
        self._failures = 0

    def start(self) -> None:
        self._usb = _import_pyusb()
        try:
            self._setup(self._find())
        except DriverUnavailableError:
            self.close()
            raise
        except self._usb.core.USBError as err:
            if err.errno in (errno.EACCES, errno.ENODEV):
                self._fail_setup(err)
            log.warning("flirone_usb_reset", reason=f"setup failed: {err}")  # wedged: what a re-plug would do
            self._reset()
            try:
                self._setup(self._find())
            except self._usb.core.USBError as again:
                self._fail_setup(again)
        log.info("flirone_usb_started", fileio_handshake=self.fileio_handshake,
                 alt_settings={f"{i}.{a}": how for (i, a), how in self.selection.items()})

    def _find(self) -> Any:
        backend = self.backend or self._usb.backend.libusb1.get_backend()
        if backend is None:
            raise DriverUnavailableError(
                "flirone: libusb-1.0 not found (pyusb has no backend); install it, e.g. apt install libusb-1.0-0"
            )
        dev = self._usb.core.find(idVendor=VENDOR_ID, idProduct=PRODUCT_ID, backend=backend)
        if dev is None:
            raise DriverUnavailableError("flirone: no FLIR One (09cb:1996) on the USB bus; plugged in?")
        self._dev = dev
        return dev

    def _fail_setup(self, err: Any) -> None:
        self.close()
        hint = " (permission denied: install systemd/99-respecd.rules)" if err.errno == errno.EACCES else ""
        raise DriverUnavailableError(f"flirone: USB setup failed: {err}{hint}") from err

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
        self._select(2, 0)  # stop frames
        self._select(1, 0)  # stop FileIO
        self._select(1, 1)  # start FileIO
        if self.fileio_handshake:
            for message in FILEIO_HANDSHAKE:
                dev.write(EP_FILEIO_OUT, message, 500)
        self._select(2, 1, VIDEO_START_TIMEOUT_MS)  # start video
        self._check_endpoints()

    def _select(self, interface: int, alt: int, timeout: int = CONTROL_TIMEOUT_MS) -> None:
        """SET_INTERFACE(interface, alt), through pyusb when the device describes that setting."""
        if self._described(interface, alt):
            self._dev.set_interface_altsetting(interface=interface, alternate_setting=alt)
            self.selection[(interface, alt)] = "pyusb"
            return
        # a setting the descriptors do not list (or one without the endpoint we read): the camera
        # takes the request as a start/stop command, the host keeps its setting (flirone-v4l2's way)
        data = b"\x00\x00" if (interface, alt) == (2, 1) else None  # the references send wLength 2 here
        self._dev.ctrl_transfer(REQ_TYPE_SET_INTERFACE, REQ_SET_INTERFACE, alt, interface, data, timeout)
        self.selection[(interface, alt)] = "raw"

    def _described(self, interface: int, alt: int) -> bool:
        cfg = self._dev.get_active_configuration()
        setting = self._usb.util.find_descriptor(cfg, bInterfaceNumber=interface, bAlternateSetting=alt)
        if setting is None:
            return False
        wanted = READ_ENDPOINT.get(interface)
        if alt == 0 or wanted is None:
            return True
        return self._usb.util.find_descriptor(setting, bEndpointAddress=wanted) is not None

    def _check_endpoints(self) -> None:
        """The endpoints we read exist in the settings now selected (pyusb's view is the kernel's)."""
        for interface, endpoint in ((0, EP_STATUS), *READ_ENDPOINT.items()):
            intf = self._dev.get_active_configuration()[(interface, self._active_alt(interface))]
            if self._usb.util.find_descriptor(intf, bEndpointAddress=endpoint) is None:
                raise DriverUnavailableError(
                    f"flirone: EP {endpoint:#04x} is not in interface {interface}'s selected setting "
                    f"({intf.bAlternateSetting}); unexpected USB layout, please report it"
                )

    def _active_alt(self, interface: int) -> int:
        picked = [alt for (i, alt), how in self.selection.items() if i == interface and how == "pyusb"]
        return picked[-1] if picked else 0

    def read(self, size: int, timeout_ms: int) -> bytes:
        usb = self._usb
        if len(self._buf) != size:  # pyusb fills an array.array in place (a memoryview is refused)
            self._buf = array.array("B", bytes(size))
        try:
            count = self._dev.read(EP_FRAMES, self._buf, timeout_ms)
        except usb.core.USBTimeoutError:
            count = 0
        except usb.core.USBError as err:
            self._bulk_error(err)
            count = 0
        else:
            self._failures = 0
        self._drain_side_endpoints()
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

    def _drain_side_endpoints(self) -> None:
        """Empty EP 0x81 and 0x83 after every frame read (the references poll both every loop)."""
        for endpoint in (EP_STATUS, EP_FILEIO):
            for _ in range(SIDE_READS_MAX):
                try:
                    data = self._dev.read(endpoint, SIDE_READ_SIZE, self.side_timeout_ms)
                except self._usb.core.USBTimeoutError:
                    break
                except self._usb.core.USBError as err:
                    if err.errno == errno.ENODEV:  # flirone-v4l2: NO_DEVICE on 0x83 -> restart
                        raise DriverUnavailableError("flirone: camera unplugged (USB no device)") from err
                    break
                if endpoint == EP_STATUS and len(data):
                    self._note_status(bytes(data))
                if len(data) < SIDE_READ_SIZE:
                    break  # a short transfer: nothing more queued

    def _note_status(self, data: bytes) -> None:
        """Log each kind of JSON message the camera sends on EP 0x81 once (the rest at debug)."""
        for message in _json_objects(data):
            kind = str(message.get("type", "?"))
            if kind not in self.status_types:
                self.status_types.add(kind)
                log.info("flirone_status", type=kind, message=json.dumps(message)[:300])
            else:
                log.debug("flirone_status", type=kind)

    def _reset(self) -> None:
        """USB port reset, as every reference does at exit: a wedged camera comes back as after a re-plug."""
        dev = self._dev
        if dev is None:
            return
        self.resets += 1
        try:
            dev.reset()
        except self._usb.core.USBError as err:  # it may re-enumerate under a new handle: find it again
            log.debug("flirone_usb_reset_error", error=str(err))
        self._usb.util.dispose_resources(dev)
        self._dev = None

    def close(self) -> None:
        dev = self._dev
        if dev is None:
            return
        usb = self._usb
        for interface in (2, 1):  # stop video, stop FileIO
            try:
                self._select(interface, 0)
            except usb.core.USBError:
                pass
        for interface in INTERFACES:
            try:
                usb.util.release_interface(dev, interface)
            except usb.core.USBError:
                pass
        self._reset()


def _json_objects(data: bytes) -> list[dict[str, Any]]:
    """JSON objects in a side-endpoint read (after binary headers, NUL-separated); bad ones skipped."""
    text = data.decode("ascii", errors="replace")
    decoder, out, at = json.JSONDecoder(), [], text.find("{")
    while at >= 0:
        try:
            obj, end = decoder.raw_decode(text, at)
        except (ValueError, RecursionError):
            at = text.find("{", at + 1)
            continue
        if isinstance(obj, dict):
            out.append(obj)
        at = text.find("{", end)
    return out


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
