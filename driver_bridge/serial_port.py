"""Serial devices in raw mode with the standard library only (termios, tty, os, select), and line framing.

`open_serial` opens a UART, a USB CDC device or a pseudo-terminal as raw 8N1 with no flow control, so
binary frames pass unchanged: no echo, no CR/LF translation, no line buffering, no signal characters.
The descriptor is non-blocking; `pump` waits with `select` and feeds what arrives to a parser until a
deadline or until enough results came out.

`LineReader` and `nmea_checksum` frame ASCII sentences the NMEA 0183 way: `$<body>*<XX>\\r\\n`, where XX is
the XOR of every byte of <body> in two upper-case hex digits (NMEA 0183; see also
https://gpsd.gitlab.io/gpsd/NMEA.html). The odometry, bearing and thruster lines use that framing.
"""

from __future__ import annotations

import math
import os
import re
import select
import termios
import time
import tty
from collections import Counter
from collections.abc import Callable, Sequence
from functools import reduce
from typing import TypeVar

T = TypeVar("T")
_HEX = frozenset(b"0123456789ABCDEFabcdef")
# A decimal as a device writes it: digits, an optional fraction and exponent. Python's float() also takes
# "nan", "inf", "1_000" and spaces, none of which a sensor sends.
_DECIMAL = re.compile(r"[+-]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]{1,4})?")


def baud_constant(baud: int) -> int:
    """The termios speed constant of `baud` (e.g. 921600 -> termios.B921600); ValueError if unsupported."""
    constant = getattr(termios, f"B{int(baud)}", None)
    if constant is None or int(baud) <= 0:
        raise ValueError(f"unsupported baud rate {baud}")
    return constant


def open_serial(path: str, baud: int) -> int:
    """Open `path` read-write as a raw 8N1 port at `baud`; returns a non-blocking file descriptor."""
    speed = baud_constant(baud)
    fd = os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)  # NOCTTY: never become our controlling tty
    try:
        tty.setraw(fd, termios.TCSANOW)
        iflag, oflag, cflag, lflag, _, _, cc = termios.tcgetattr(fd)
        iflag &= ~(termios.IXON | termios.IXOFF | termios.IXANY)       # no software flow control
        cflag = (cflag & ~(termios.CSIZE | termios.PARENB | termios.CSTOPB)) | termios.CS8
        cflag |= termios.CLOCAL | termios.CREAD                        # ignore modem lines, enable receiver
        if hasattr(termios, "CRTSCTS"):
            cflag &= ~termios.CRTSCTS                                  # no hardware flow control
        cc[termios.VMIN], cc[termios.VTIME] = 0, 0                     # reads return what is there
        termios.tcsetattr(fd, termios.TCSANOW, [iflag, oflag, cflag, lflag, speed, speed, cc])
    except BaseException:
        os.close(fd)
        raise
    return fd


def read_available(fd: int, timeout_s: float, size: int = 4096) -> bytes:
    """Bytes ready on `fd` within `timeout_s` (b"" if none came)."""
    ready, _, _ = select.select([fd], [], [], max(0.0, timeout_s))
    if not ready:
        return b""
    try:
        return os.read(fd, size)
    except BlockingIOError:
        return b""


def write_all(fd: int, data: bytes, timeout_s: float = 1.0) -> None:
    """Write every byte of `data` to a non-blocking `fd`; TimeoutError if the device will not take them."""
    view, deadline = memoryview(data), time.monotonic() + timeout_s
    while view:
        _, ready, _ = select.select([], [fd], [], max(0.0, deadline - time.monotonic()))
        if not ready:
            raise TimeoutError(f"serial write stalled with {len(view)} bytes left")
        view = view[os.write(fd, view):]


def pump(fd: int, feed: Callable[[bytes], Sequence[T]], timeout_s: float, want: int | None = None) -> list[T]:
    """Read from `fd` and pass every chunk to `feed` until `timeout_s` passes or `want` results came out."""
    results: list[T] = []
    deadline = time.monotonic() + timeout_s
    while (remaining := deadline - time.monotonic()) > 0 and (want is None or len(results) < want):
        chunk = read_available(fd, min(remaining, 0.05))
        if chunk:
            results.extend(feed(chunk))
    return results


def nmea_checksum(body: bytes) -> int:
    """XOR of every byte between `$` and `*` (NMEA 0183)."""
    return reduce(lambda acc, byte: acc ^ byte, body, 0)


def nmea_sentence(body: str) -> bytes:
    """`$<body>*<XX>\\r\\n` with its checksum."""
    raw = body.encode("ascii")
    return b"$" + raw + b"*" + f"{nmea_checksum(raw):02X}".encode() + b"\r\n"


def nmea_number(text: str) -> float | None:
    """The finite number a sentence's field holds, or None (empty, not a plain decimal, or beyond a float)."""
    if not _DECIMAL.fullmatch(text):
        return None
    value = float(text)
    return value if math.isfinite(value) else None


class LineReader:
    """Split a byte stream into checked NMEA-style sentences; `feed` returns their bodies (without $ and *XX).

    Refusals are counted in `rejected` by reason: `bad_checksum`, `malformed` (no `$...*XX`), `too_long`
    (a line longer than `max_line` bytes, most likely a lost line end).
    """

    def __init__(self, max_line: int = 256):
        self.max_line = max_line
        self.rejected: Counter[str] = Counter()
        self._buffer = bytearray()

    def feed(self, data: bytes) -> list[bytes]:
        self._buffer += data
        bodies = []
        while (end := self._buffer.find(b"\n")) >= 0:
            line = bytes(self._buffer[:end]).strip()
            del self._buffer[: end + 1]
            if line:
                body = self._check(line)
                if body is not None:
                    bodies.append(body)
        if len(self._buffer) > self.max_line:  # keep memory bounded when line ends go missing
            self.rejected["too_long"] += 1
            self._buffer.clear()
        return bodies

    def _check(self, line: bytes) -> bytes | None:
        if len(line) > self.max_line:
            self.rejected["too_long"] += 1
            return None
        start, star = line.rfind(b"$"), line.rfind(b"*")
        if start < 0 or star < start or len(line) != star + 3:
            self.rejected["malformed"] += 1
            return None
        body = line[start + 1: star]
        digits = line[star + 1:]
        if not all(c in _HEX for c in digits) or int(digits, 16) != nmea_checksum(body):
            self.rejected["bad_checksum"] += 1
            return None
        return body
