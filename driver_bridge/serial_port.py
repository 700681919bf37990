"""Serial devices on pyserial, and NMEA 0183 sentences on pynmeagps (both from the `driver` extra).

`open_serial` opens a UART, a USB CDC device or a pseudo-terminal with pyserial as raw 8N1 with no flow
control, so binary frames pass unchanged (no echo, no CR/LF translation, no signal characters); its reads
return what is there (timeout 0) and its writes give up after `write_timeout` (SerialTimeoutException, an
OSError). The bridge waits on all its ports at once with `select` (a pyserial port has a fileno);
`read_available`, `write_all` and `pump` serve one port or a bare descriptor (a pseudo-terminal's other end).

`LineReader` splits a byte stream into lines (bounded by `max_line`) and keeps the sentences `$<body>*<XX>`
whose checksum pynmeagps finds right: XX is the XOR of every byte of <body> in two hex digits (NMEA 0183;
https://gpsd.gitlab.io/gpsd/NMEA.html). `read_sentence` gives a standard sentence's fields by name from
pynmeagps's tables; `nmea_number` is the strict rule every number field meets. The odometry, bearing and
thruster lines use this framing.

Without the extra, `libraries` raises an ImportError whose message is the install line.
"""

from __future__ import annotations

import math
import os
import re
import select
import time
from collections import Counter
from collections.abc import Callable, Sequence
from typing import Any, TypeVar

T = TypeVar("T")
DRIVER_EXTRA = "pip install 'usv-circumnav[driver]'"
# A decimal as a device writes it: digits, an optional fraction and exponent. Python's float() (and so
# pynmeagps) also takes "nan", "inf", "1_000" and spaces, none of which a sensor sends.
_DECIMAL = re.compile(r"[+-]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]{1,4})?")
_INTEGER = re.compile(r"[0-9]{1,9}")
_DEGREES_MINUTES = re.compile(r"[0-9]{2,3}[0-5][0-9]\.[0-9]{1,9}")   # NMEA's (d)ddmm.mmm
_loaded: tuple[Any, Any] | None = None


def libraries() -> tuple[Any, Any]:
    """(serial, pynmeagps), or an ImportError that says how to get them (the boats' `driver` extra)."""
    global _loaded
    if _loaded is None:
        try:
            import pynmeagps
            import serial
        except ImportError as error:
            raise ImportError(f"the driver bridge needs pyserial and pynmeagps ({error.name} is missing): "
                              f"{DRIVER_EXTRA}") from None
        if not hasattr(serial, "Serial"):   # the unrelated PyPI package `serial` takes the same name
            where = serial.__file__
            raise ImportError(f"the driver bridge needs pyserial, but the module `serial` at {where} is "
                              f"another package: pip uninstall serial, then {DRIVER_EXTRA}")
        _loaded = serial, pynmeagps
    return _loaded


def open_serial(path: str, baud: int, write_timeout: float = 1.0):
    """`path` opened read-write as a raw 8N1 port at `baud`: a pyserial Serial whose reads never block."""
    serial, _ = libraries()
    return serial.Serial(path, int(baud), bytesize=serial.EIGHTBITS, parity=serial.PARITY_NONE,
                         stopbits=serial.STOPBITS_ONE, timeout=0, write_timeout=write_timeout,
                         xonxoff=False, rtscts=False, dsrdtr=False)


def _descriptor(port) -> int:
    return port if isinstance(port, int) else port.fileno()


def read_available(port, timeout_s: float, size: int = 4096) -> bytes:
    """Bytes ready on `port` (a pyserial port or a descriptor) within `timeout_s` (b"" if none came)."""
    ready, _, _ = select.select([port], [], [], max(0.0, timeout_s))
    if not ready:
        return b""
    if not isinstance(port, int):
        return port.read(size)
    try:
        return os.read(port, size)
    except BlockingIOError:
        return b""


def write_all(port, data: bytes, timeout_s: float = 1.0) -> None:
    """Write every byte of `data` to `port` (a pyserial port or a non-blocking descriptor); TimeoutError if
    the device will not take them within `timeout_s`."""
    fd, view, deadline = _descriptor(port), memoryview(data), time.monotonic() + timeout_s
    while view:
        _, ready, _ = select.select([], [fd], [], max(0.0, deadline - time.monotonic()))
        if not ready:
            raise TimeoutError(f"serial write stalled with {len(view)} bytes left")
        view = view[os.write(fd, view):]


def pump(port, feed: Callable[[bytes], Sequence[T]], timeout_s: float, want: int | None = None) -> list[T]:
    """Read from `port` and pass every chunk to `feed` until `timeout_s` passes or `want` results came out."""
    results: list[T] = []
    deadline = time.monotonic() + timeout_s
    while (remaining := deadline - time.monotonic()) > 0 and (want is None or len(results) < want):
        chunk = read_available(port, min(remaining, 0.05))
        if chunk:
            results.extend(feed(chunk))
    return results


def _text(body: bytes) -> str:
    # One character a byte, so that pynmeagps's checksum (over characters) is the XOR of the bytes.
    return body.decode("latin-1")


def nmea_checksum(body: bytes) -> int:
    """XOR of every byte between `$` and `*` (NMEA 0183), by pynmeagps."""
    return int(libraries()[1].calc_checksum(_text(body)), 16)


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


def read_sentence(body: bytes, msg_id: str, fields: int):
    """(pynmeagps's NMEAMessage, "") for a checked body of standard sentence `msg_id` with exactly `fields`
    fields after its address, its fields typed and named by pynmeagps's table; else (None, why):
    `not_<msg_id>` (another sentence, or another number of fields) or `bad_number` (a field of the table
    that is neither empty nor what its kind holds: a plain finite decimal, digits, (d)ddmm.mmm with minutes
    below 60, a time hhmmss[.ss])."""
    _, nmea = libraries()
    content = _text(body)
    address, *payload = content.split(",")
    talker, found = (address[:1], address[1:]) if address[:1] == "P" else (address[:2], address[2:])
    if found != msg_id or len(payload) != fields:
        return None, f"not_{msg_id.lower()}"
    table = list(nmea.NMEA_PAYLOADS_GET[msg_id].items())
    rules = {nmea.DE: lambda text: nmea_number(text) is not None, nmea.IN: _INTEGER.fullmatch,
             nmea.LA: _DEGREES_MINUTES.fullmatch, nmea.LN: _DEGREES_MINUTES.fullmatch}
    if any(text and not rules.get(kind, bool)(text) for (_, kind), text in zip(table, payload)):
        return None, "bad_number"
    try:
        message = nmea.NMEAMessage(talker, msg_id, nmea.GET, payload=payload, validate=nmea.VALNONE)
    except nmea.NMEATypeError:   # a field of another kind that is not one
        return None, "bad_number"
    # pynmeagps gives "" for a time or position it cannot read (e.g. an hour of 25), without a word
    if any(text and kind in (nmea.TM, nmea.LA, nmea.LN) and getattr(message, name) == ""
           for (name, kind), text in zip(table, payload)):
        return None, "bad_number"
    return message, ""


class LineReader:
    """Split a byte stream into checked NMEA-style sentences; `feed` returns their bodies (without $ and *XX).

    Refusals are counted in `rejected` by reason: `bad_checksum` (pynmeagps finds the checksum wrong),
    `malformed` (no `$...*XX`), `too_long` (a line longer than `max_line` bytes, most likely a lost line end).
    Bytes before a line's last `$` are skipped (noise, or the end of a line cut short).
    """

    def __init__(self, max_line: int = 256):
        self.max_line = max_line
        self.rejected: Counter[str] = Counter()
        self._buffer = bytearray()
        self._nmea = libraries()[1]

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
        try:
            content, _, _, _, checksum = self._nmea.get_parts(_text(line[start:]))
        except self._nmea.NMEAMessageError:
            self.rejected["malformed"] += 1
            return None
        if checksum.upper() != self._nmea.calc_checksum(content):
            self.rejected["bad_checksum"] += 1
            return None
        return content.encode("latin-1")
