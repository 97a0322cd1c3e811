"""An IWR6843 running the out-of-box demo, on two pseudo-terminals (shared by the radar tests).

A thread answers the CLI port like the demo (echo, ``Done``/errors, prompt, boot garbage,
its own crash text) and, between ``sensorStart`` and ``sensorStop``, streams the packets of
a real IWR6843 capture on the data port with the frame counter restarting at 1 as the
radar does. Faults are switches on the instance: rejected or unanswered lines, a silent or
garbage data port, a hung radar.
"""

from __future__ import annotations

import contextlib
import os
import pty
import random
import select
import struct
import threading
import time
import tty
from collections.abc import Callable
from pathlib import Path

import pytest

from respecd.radar.cli_port import PROMPT
from respecd.radar.tlv import MAGIC

REAL = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real"
CAPTURE = REAL / "ti_iwr6843_oob_automated_doors" / "xwr68xx_processed_stream_2019_12_04T21_44_51_663.dat"


def split_packets(data: bytes) -> list[bytes]:
    """The capture cut at its own packet boundaries: magic word + totalPacketLen (offset 12)."""
    packets, at = [], data.find(MAGIC)
    while at >= 0 and at + 16 <= len(data):
        length = struct.unpack_from("<I", data, at + 12)[0]
        if length < 40 or at + length > len(data):
            break
        packets.append(data[at:at + length])
        at = data.find(MAGIC, at + length)
    return packets


def capture_frames() -> list[bytes]:
    if not CAPTURE.exists():
        pytest.skip(f"shared capture {CAPTURE} absent (CI clones shared/ beside the repo)")
    return split_packets(CAPTURE.read_bytes())  # 101 packets of 608-1088 B (18 of them 768 B)


def radar_config(fake: FakeRadar, **settings: object):
    """An iwr6843 profile entry on ``fake``'s two ports (the tests' timeouts in ``settings``)."""
    from respecd.drivers.iwr6843 import IWR6843Config

    return IWR6843Config(name="radar", cli_port=str(fake.cli_path), data_port=str(fake.data_path), **settings)


class FakeRadar:
    """An IWR6843 on two pseudo-terminals, reachable through symlinks in ``folder``."""

    def __init__(self, folder: Path, frames: list[bytes], garbage_first: bool = True,
                 reject: tuple[str, ...] = (), silent: bool = False, renumber: bool = True) -> None:
        self.frames, self.reject, self.silent, self.renumber = frames, reject, silent, renumber
        self.reject_line: Callable[[str], bool] = lambda line: False  # refuse matching lines ("Error -1")
        self.no_done: Callable[[str], bool] = lambda line: False  # echo matching lines, never say Done
        self.data_mode = "frames"  # frames | silent (CLI fine, data port quiet) | garbage (random bytes)
        self.mangle: Callable[[int, bytes], bytes] = lambda index, frame: frame  # damage the index-th packet sent
        self.commands: list[str] = []
        self.streaming = threading.Event()
        self.mute = threading.Event()  # stop streaming without being told (a hung radar)
        self._stop = threading.Event()
        self._rx = b"\x00\xfe\xff" if garbage_first else b""  # boot garbage already in the UART receiver
        self._fds: list[int] = []
        self.cli_path, self.data_path = folder / "radar-cli", folder / "radar-data"
        self._cli = self._pty(self.cli_path)
        self._data = self._pty(self.data_path)
        self._threads = [threading.Thread(target=self._cli_loop, name="fake-cli"),
                         threading.Thread(target=self._data_loop, name="fake-data")]
        for thread in self._threads:
            thread.start()

    def _pty(self, link: Path) -> int:
        master, slave = pty.openpty()
        tty.setraw(slave)
        os.set_blocking(master, False)  # a full UART drops bytes; the fake never blocks
        with contextlib.suppress(FileNotFoundError):
            link.unlink()
        link.symlink_to(os.ttyname(slave))
        self._fds += [master, slave]
        return master

    def unplug(self) -> None:
        self._stop.set()
        for thread in self._threads:
            thread.join(2)
        for fd in self._fds:
            os.close(fd)
        for link in (self.cli_path, self.data_path):
            with contextlib.suppress(FileNotFoundError):
                link.unlink()

    def say(self, text: str) -> None:
        """Print on the CLI port unasked, as the demo does when it crashes."""
        self._write(self._cli, text.encode())

    def since_last(self, command: str) -> list[str]:
        """The commands after the last ``command``."""
        last = max(i for i, line in enumerate(self.commands) if line == command)
        return self.commands[last + 1:]

    def _write(self, fd: int, data: bytes) -> None:
        with contextlib.suppress(BlockingIOError, OSError):
            os.write(fd, data)

    def _cli_loop(self) -> None:
        while not self._stop.is_set():
            ready, _, _ = select.select([self._cli], [], [], 0.02)
            if not ready:
                continue
            try:
                self._rx += os.read(self._cli, 4096)
            except OSError:
                continue
            while b"\n" in self._rx:
                line, self._rx = self._rx.split(b"\n", 1)
                self._answer(line.rstrip(b"\r"))

    def _answer(self, raw: bytes) -> None:
        text = raw.decode("ascii", errors="replace")
        if self.silent:
            return
        if not text.isprintable():
            self._write(self._cli, f"'{text}' is not recognized as a CLI command\r\nError -1\r\n{PROMPT}".encode())
            return
        if not text:
            self._write(self._cli, PROMPT.encode())
            return
        self.commands.append(text)
        command = text.split()[0]
        reply = f"{text}\r\n"
        if command in self.reject or self.reject_line(text):
            self._write(self._cli, f"{reply}Error -1\r\n{PROMPT}".encode())
            return
        if self.no_done(text):
            self._write(self._cli, reply.encode())
            return
        if command == "sensorStop":
            if not self.streaming.is_set():
                reply += "Ignored: Sensor is already stopped\r\n"
            self.streaming.clear()
        elif command == "sensorStart":
            time.sleep(0.02)  # RF calibration before the first chirp
            self.mute.clear()
            self.streaming.set()
        self._write(self._cli, f"{reply}Done\r\n{PROMPT}".encode())

    def _data_loop(self) -> None:
        index, number, noise = 0, 1, random.Random(7)
        while not self._stop.is_set():
            if not self.streaming.is_set() or self.mute.is_set() or self.data_mode == "silent":
                number = 1  # the demo restarts frame numbering at sensorStart
                time.sleep(0.005)
                continue
            if self.data_mode == "garbage":
                self._write(self._data, noise.randbytes(700))
                time.sleep(0.01)
                continue
            frame = bytearray(self.frames[index % len(self.frames)])
            if self.renumber:
                struct.pack_into("<I", frame, 20, number)  # out-of-box header: frameNumber at offset 20
            self._write(self._data, self.mangle(index, bytes(frame)))
            index, number = index + 1, number + 1
            time.sleep(0.01)
