"""OpenCV's own log lines (``[ WARN:0@0.03] global cap_v4l.cpp:914 open ...``), written by
its C++ code straight to file descriptor 2, logged as ``opencv`` events like every other
line instead of landing raw in the JSON stream.

``StderrRelay`` puts a pipe on fd 2 and reads it in a thread: OpenCV's lines become
structlog events at their level, anything else (a traceback, another library's text) is
passed to the real stderr unchanged. ``stop`` puts the real stderr back and drains the pipe,
so nothing written before it is lost.
"""

from __future__ import annotations

import os
import re
import threading

import structlog

log = structlog.get_logger("opencv")

OPENCV_LINE = re.compile(rb"^\[\s*(FATAL|ERROR|WARN|INFO|DEBUG|VERBOSE)[^\]]*\]\s*(?:global\s+)?(.*)$")
LEVELS = {b"FATAL": "critical", b"ERROR": "error", b"WARN": "warning", b"INFO": "info", b"DEBUG": "debug",
          b"VERBOSE": "debug"}


class StderrRelay:
    def __init__(self) -> None:
        self._saved: int | None = None
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        read_end, write_end = os.pipe()
        self._saved = os.dup(2)
        os.dup2(write_end, 2)
        os.close(write_end)
        self._thread = threading.Thread(target=self._run, args=(read_end,), name="respecd-stderr", daemon=True)
        self._thread.start()

    def _run(self, fd: int) -> None:
        pending = b""
        with os.fdopen(fd, "rb", buffering=0) as pipe:
            while chunk := pipe.read(65536):
                pending += chunk
                *lines, pending = pending.split(b"\n")
                for line in lines:
                    self._line(line)
        if pending:
            self._line(pending)

    def _line(self, line: bytes) -> None:
        match = OPENCV_LINE.match(line)
        if match is None:
            if self._saved is not None:
                os.write(self._saved, line + b"\n")
            return
        level = LEVELS[match.group(1)]
        getattr(log, level)("opencv", message=match.group(2).decode("utf-8", "replace").strip())

    def stop(self) -> None:
        saved, thread = self._saved, self._thread
        if saved is None or thread is None:
            return
        os.dup2(saved, 2)  # closes the pipe's last write end: the thread reads to EOF and ends
        thread.join(2.0)
        os.close(saved)
        self._saved = self._thread = None
