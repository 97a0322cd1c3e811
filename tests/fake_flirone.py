"""A FLIR One (09cb:1996) as a pyusb backend: the real pyusb library runs on top of it.

Descriptors as public reports give them: the device descriptor from libusb issue #729's
macOS dump (bcdUSB 2.00, class 0, bcdDevice 1.08, strings 1/2/3, one configuration whose
value is 3, high speed), interface class 0xFF / subclass 0xF0 (libuvc issue #168), and one
bulk IN + OUT pair per interface (0: 0x81/0x02, 1: 0x83/0x04, 2: 0x85/0x06: the endpoint
numbers a rusb FLIR One driver enumerates). Where the endpoints sit among the alternate
settings differs between reports, so ``layout`` selects one:

* ``alt1``: interfaces 1 and 2 have no endpoints in alternate setting 0 and the streaming
  pair in setting 1 (the layout issue 21 reports; a host that keeps setting 0 cannot read);
* ``alt0``: only setting 0, with the endpoints (what flirone-v4l2's raw request works on);
* ``glass``: setting 0 with the endpoints, setting 1 described with none (a Google Glass
  port's notes: "Interface 2 Alt 1 has NO endpoints - must use Alt 0").

The fake also plays the host kernel: a read on an endpoint that the interface's selected
setting (as set through ``set_interface_altsetting``) lacks fails like Linux usbfs (ENOENT).
The camera side streams only after SET_INTERFACE(2, 1) arrived, however it was sent; it
queues a status message on EP 0x81 every few frame reads and stops sending frames while more
than ``side_capacity`` of them wait undrained.
"""

from __future__ import annotations

import array
import errno
import json
from types import SimpleNamespace

import usb.backend
import usb.core

ENDPOINTS = {0: (0x81, 0x02), 1: (0x83, 0x04), 2: (0x85, 0x06)}
LAYOUTS = {  # interface -> endpoints per alternate setting
    "alt1": {0: [ENDPOINTS[0]], 1: [(), ENDPOINTS[1]], 2: [(), ENDPOINTS[2]]},
    "alt0": {0: [ENDPOINTS[0]], 1: [ENDPOINTS[1]], 2: [ENDPOINTS[2]]},
    "glass": {0: [ENDPOINTS[0]], 1: [ENDPOINTS[1], ()], 2: [ENDPOINTS[2], ()]},
}


def _desc(**fields) -> SimpleNamespace:
    return SimpleNamespace(bLength=0, extra_descriptors=[], **fields)


def usb_error(code: int) -> usb.core.USBError:
    return usb.core.USBError(errno.errorcode[code], -1, code)


def timeout_error() -> usb.core.USBTimeoutError:
    return usb.core.USBTimeoutError("Operation timed out", -7, errno.ETIMEDOUT)


class FlirBackend(usb.backend.IBackend):
    """A FLIR One that streams recorded EP 0x85 reads; records every request in ``log``."""

    def __init__(self, chunks: list[bytes], layout: str = "alt1", fail: dict | None = None,
                 status_every: int = 0, side_capacity: int = 3, wedged_until_reset: bool = False) -> None:
        self.chunks = list(chunks)
        self.layout = LAYOUTS[layout]
        self.fail = fail or {}
        self.log: list[tuple] = []
        self.configuration = 0
        self.host_alt: dict[int, int] = {}  # what the host (kernel, pyusb) selected
        self.device_alt: dict[int, int] = {}  # what the camera was told, raw or not
        self.status_every, self.side_capacity = status_every, side_capacity
        self.status_queue: list[bytes] = []
        self.frame_reads = 0
        self.wedged = wedged_until_reset

    def _maybe_fail(self, what: str) -> None:
        if self.fail.get(what):
            raise self.fail[what].pop(0)

    # descriptors
    def enumerate_devices(self):
        yield "flir"

    def get_device_descriptor(self, dev):
        return _desc(bDescriptorType=1, bcdUSB=0x200, bDeviceClass=0, bDeviceSubClass=0, bDeviceProtocol=0,
                     bMaxPacketSize0=64, idVendor=0x09CB, idProduct=0x1996, bcdDevice=0x108, iManufacturer=1,
                     iProduct=2, iSerialNumber=3, bNumConfigurations=1, address=11, bus=1, port_number=2,
                     port_numbers=(2,), speed=3)

    def get_configuration_descriptor(self, dev, config):
        return _desc(bDescriptorType=2, wTotalLength=0, bNumInterfaces=3, bConfigurationValue=3,
                     iConfiguration=0, bmAttributes=0x80, bMaxPower=250)

    def get_interface_descriptor(self, dev, intf, alt, config):
        settings = self.layout.get(intf)
        if settings is None or alt >= len(settings):  # pyusb probes settings until IndexError
            raise IndexError(intf)
        return _desc(bDescriptorType=4, bInterfaceNumber=intf, bAlternateSetting=alt,
                     bNumEndpoints=len(settings[alt]), bInterfaceClass=0xFF, bInterfaceSubClass=0xF0,
                     bInterfaceProtocol=0, iInterface=0)

    def get_endpoint_descriptor(self, dev, ep, intf, alt, config):
        return _desc(bDescriptorType=5, bEndpointAddress=self.layout[intf][alt][ep], bmAttributes=2,
                     wMaxPacketSize=512, bInterval=0, bRefresh=0, bSynchAddress=0)

    # requests
    def open_device(self, dev):
        return "handle"

    def close_device(self, dev_handle):
        self.log.append(("close",))

    def set_configuration(self, dev_handle, config_value):
        self._maybe_fail("set_configuration")
        self.configuration = config_value
        self.host_alt, self.device_alt = {}, {}
        self.log.append(("set_configuration", config_value))

    def get_configuration(self, dev_handle):
        return self.configuration

    def claim_interface(self, dev_handle, intf):
        self.log.append(("claim", intf))

    def release_interface(self, dev_handle, intf):
        self.log.append(("release", intf))

    def is_kernel_driver_active(self, dev_handle, intf):
        return False

    def set_interface_altsetting(self, dev_handle, intf, altsetting):
        """The kernel sends SET_INTERFACE and switches its own endpoint table."""
        self._set_interface(intf, altsetting, b"", CONTROL_TIMEOUT_MS)
        self.host_alt[intf] = altsetting
        self.log.append(("set_interface", intf, altsetting))

    def ctrl_transfer(self, dev_handle, bmRequestType, bRequest, wValue, wIndex, data, timeout):
        self.log.append(("ctrl", bmRequestType, bRequest, wValue, wIndex, bytes(data), timeout))
        if (bmRequestType, bRequest) == (0x01, 0x0B):  # SET_INTERFACE behind the host's back
            self._set_interface(wIndex, wValue, bytes(data), timeout)
        return len(data)

    def _set_interface(self, intf, alt, data, timeout) -> None:
        if self.wedged:
            raise timeout_error()  # a camera left in a bad state answers nothing until reset
        self._maybe_fail("set_interface")
        self.device_alt[intf] = alt

    def reset_device(self, dev_handle):
        self.log.append(("reset",))
        self.wedged = False
        self.configuration, self.host_alt, self.device_alt = 0, {}, {}

    def bulk_write(self, dev_handle, ep, intf, data, timeout):
        self.log.append(("write", ep, bytes(data)))
        return len(data)

    def bulk_read(self, dev_handle, ep, intf, buff, timeout):
        if ep not in self.layout[intf][self.host_alt.get(intf, 0)]:
            raise usb_error(errno.ENOENT)  # usbfs: no such endpoint in the selected setting
        if ep != 0x85:
            self.log.append(("poll", ep, timeout))
            if ep == 0x81 and self.status_queue:
                message = self.status_queue.pop(0)
                buff[: len(message)] = array.array("B", message)
                return len(message)
            raise timeout_error()
        self._maybe_fail("bulk_read")
        self.log.append(("read", ep))
        streaming = self.device_alt.get(2) == 1
        if not streaming or not self.chunks or len(self.status_queue) > self.side_capacity:
            raise timeout_error()
        self.frame_reads += 1
        if self.status_every and self.frame_reads % self.status_every == 0:
            self.status_queue.append(status_message(self.frame_reads))
        chunk = self.chunks.pop(0)
        buff[: len(chunk)] = array.array("B", chunk)
        return len(chunk)

    def clear_halt(self, dev_handle, ep):
        self.log.append(("clear_halt", ep))


CONTROL_TIMEOUT_MS = 100


def status_message(n: int) -> bytes:
    """A config-channel message: a 16-byte header, then NUL-terminated JSON (Android driver's reading)."""
    body = json.dumps({"type": "batteryVoltageUpdate", "data": {"voltage": 3.9, "n": n}}).encode() + b"\x00"
    return b"\xcc\x01\x00\x00\x01\x00\x00\x00" + len(body).to_bytes(4, "little") + b"\x00" * 4 + body
