"""The console of one process of a fleet run: what it prints, read from its pipe by the launcher and written
to `<name>.log` in the run folder, whatever that folder's disk does.

A child writes to a pipe, never to the run folder's disk, so a full disk cannot fail a child's print (and end
it from inside its error handling). The launcher's thread writes what comes to the file; while the file
cannot be written (ENOSPC, EDQUOT, any OSError) it keeps the last `TAIL_BYTES` in memory, counts what falls
out of that tail, and tries the file again at most every `RETRY_SECONDS`. When a write succeeds again the
file gets one marker line saying what was lost, from when to when, and then the tail kept. If the disk is
still full when the run ends, the launcher says so in one line with each console's last line
(`Console.close`). Lines in which a process says its log is suspended (`mcap_log.SUSPENDED`) are noted.
"""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Callable
from pathlib import Path

from agent.runtime.mcap_log import SUSPENDED

TAIL_BYTES = 64 * 1024   # of a console kept in memory while its file cannot be written
RETRY_SECONDS = 1.0      # between tries of a file that failed
READ_BYTES = 64 * 1024


def _clock(wall: float) -> str:
    return time.strftime("%H:%M:%S", time.localtime(wall)) + f".{int(wall % 1 * 10)}"


class Console:
    """Relays a child's output from `pipe` (its stdout and stderr, binary) to `path`; `failed(error)` is
    called the first time the file cannot be written (the launcher says it once on its own stderr), and
    `suspended(line)` the first time the process says its log is suspended."""

    def __init__(self, path: Path, pipe, failed: Callable[[str, OSError], None] | None = None,
                 suspended: Callable[[str], None] | None = None) -> None:
        self.path = path
        self.last_line = ""
        self.logs_suspended = False     # the process said its MCAP log is suspended
        self.lost_bytes = 0             # fell out of the tail while the file could not be written
        self.failures = 0               # writes (or opens) of the file that failed
        self._pipe = pipe
        self._failed = failed
        self._suspended = suspended
        self._recent = bytearray()      # the last TAIL_BYTES of the console, written or not (`text`)
        self._file = None
        self._tail = bytearray()        # not yet written (while failing)
        self._since: float | None = None    # wall time the file first failed, in the current failure
        self._error: OSError | None = None
        self._next_try = 0.0
        self._partial = b""
        self._lock = threading.Lock()
        self._open()
        self._thread = threading.Thread(target=self._relay, name=f"console {path.name}", daemon=True)
        self._thread.start()

    # ----- the file -----
    def _open(self) -> bool:
        if self._file is not None:
            return True
        try:
            self._file = self.path.open("ab", buffering=0)
            return True
        except OSError as error:
            self._fail(error)
            return False

    def _fail(self, error: OSError) -> None:
        self.failures += 1
        if self._since is None:
            self._since, self._error = time.time(), error
            if self._failed is not None and self.failures == 1:
                self._failed(self.path.name, error)
        self._next_try = time.monotonic() + RETRY_SECONDS

    def _write_all(self, data: bytes) -> int:
        """Bytes of `data` written to the file before an OSError (all of them: len(data))."""
        done = 0
        try:
            while done < len(data):
                done += self._file.write(data[done:]) or 0
        except OSError as error:
            self._fail(error)
        return done

    def _put(self, data: bytes) -> None:
        """`data` to the file, after the tail kept since a failure; what cannot be written joins the tail."""
        self._tail += data
        if self._since is not None and time.monotonic() < self._next_try:
            self._bound_tail()
            return
        if not self._open():
            self._bound_tail()
            return
        if self._since is not None:
            marker = (f"[usv-fleet: this console could not be written from {_clock(self._since)} to "
                      f"{_clock(time.time())} ({type(self._error).__name__}: {self._error}); "
                      f"{self.lost_bytes} byte(s) lost; the last {len(self._tail)} byte(s) before now "
                      "follow]\n").encode()
            if self._write_all(marker) < len(marker):
                self._bound_tail()
                return
            self._since, self._error, self.lost_bytes = None, None, 0
        done = self._write_all(bytes(self._tail))
        del self._tail[:done]
        self._bound_tail()

    def _bound_tail(self) -> None:
        extra = len(self._tail) - TAIL_BYTES
        if extra > 0:
            del self._tail[:extra]
            self.lost_bytes += extra

    # ----- the relay -----
    def _relay(self) -> None:
        fd = self._pipe.fileno()
        while True:
            try:
                data = os.read(fd, READ_BYTES)
            except OSError:
                data = b""
            if not data:
                break
            self._note(data)
            with self._lock:
                self._put(data)

    def _note(self, data: bytes) -> None:
        self._recent += data
        del self._recent[:max(0, len(self._recent) - TAIL_BYTES)]
        text = self._partial + data
        lines = text.split(b"\n")
        self._partial = lines.pop()[-4096:]
        for line in lines:
            if not self.logs_suspended and SUSPENDED.encode() in line:
                self.logs_suspended = True
                if self._suspended is not None:
                    self._suspended(line.decode(errors="replace").strip())
        for line in reversed(lines):
            if line.strip():
                self.last_line = line.decode(errors="replace").strip()
                break

    @property
    def text(self) -> str:
        """The console's last TAIL_BYTES, as text."""
        return self._recent.decode(errors="replace")

    def drain(self, timeout: float = 2.0) -> None:
        """Once the process has exited: wait (bounded) for the rest of its output to be read."""
        self._thread.join(timeout)

    def close(self, timeout: float = 5.0) -> str | None:
        """After the process has exited: the rest of its output, a last try of the file. None if the console
        is all in its file; else a line saying what is not, with its last line."""
        self.drain(timeout)
        with self._lock:
            if self._partial.strip():
                self.last_line = self._partial.decode(errors="replace").strip()
            if self._tail or self._since is not None:
                self._next_try = 0.0
                self._put(b"")
            unwritten = len(self._tail) + self.lost_bytes
            error = self._error
            if self._file is not None:
                try:
                    self._file.close()
                except OSError:
                    pass
            self._pipe.close()
        if not unwritten:
            return None
        kind = type(error).__name__ if error else "OSError"
        return (f"{self.path.name} not written in full ({kind}: {error}): {unwritten} byte(s) lost; its last "
                f"line: {self.last_line or '(none)'}")
