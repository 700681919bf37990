"""MCAP logs: what a process received, published and decided, as JSON with JSON schemas.

Each topic gets a channel whose schema is the JSON schema of the pydantic model logged on it (or one given),
so a file opens in Foxglove and every field can be plotted. The chunk in progress is written out at least
every `flush_seconds` of wall time: a process killed hard loses at most about that much, and
`read_messages` reads an unfinished file up to its last complete chunk.

Every file records its log format in a metadata record `usv-log-format` (`version`), written first with
the `run` metadata and the `usv-log-part` record (which set of parts the file belongs to, and its place
in it): a reader checks the version before reading on (mission_log/reader.py). A message's JSON may gain
fields within a version; a change an older reader would misread needs a new version.

**Rotation** (`rotation=LogRotation(...)`; none by default). The log is cut into parts by size and/or
time: the first part is the path given (`agent-1.mcap`), the next ones `agent-1.part0001.mcap`,
`agent-1.part0002.mcap`, ... (they sort in time order after the first). Each part is a complete MCAP file
with the format, run and part records, so any part reads on its own; `mission_log.reader` joins the parts
of a set into one log. Once the closed parts would leave no room for a full current part within
`max_total_mb`, the oldest are deleted, so the set stays within the bound (plus at most one flush).

**Write errors** (ENOSPC, EDQUOT, any OSError of a write) suspend the log, never the caller: later
messages are dropped and counted, and a new part, opened when there is room, starts with a `/log/gap`.

More: docs/logs.md, "The modules in detail", `agent/runtime/mcap_log.py`.
"""

from __future__ import annotations

import contextlib
import json
import stat
import struct
import sys
import time
import uuid
import warnings
from collections.abc import Callable, Iterator
from pathlib import Path

import orjson
from mcap.exceptions import McapError
from mcap.stream_reader import Channel, Message, Metadata, StreamReader
from mcap.writer import CompressionType, Writer
from pydantic import BaseModel, Field, model_validator

from agent.config import PositiveFloat, StrictModel

PROFILE = ""  # plain JSON messages, no ROS profile
NUMPY = orjson.OPT_SERIALIZE_NUMPY
FORMAT_RECORD = "usv-log-format"   # metadata record: {"version": FORMAT_VERSION}
FORMAT_VERSION = "5"               # 2: inputs carry range_stamp; 3: and earlier_ranges; 4: shared estimates a stamp; 5: each pair's observability in the estimates, its path spread in the state. The channels of agent/runtime/log_schema.py, the `run` metadata
PART_RECORD = "usv-log-part"       # metadata record: {"set": id shared by a log's parts, "part": "0", "first": file name}
PART_WIDTH = 4                     # agent-1.part0001.mcap
MB = 1_000_000
GAP_TOPIC = "/log/gap"             # the first message of a part started after a write failure (LogGap)
SUSPENDED = "logging suspended"    # how the announcement of a failure starts (the launcher looks for it)
RETRY_SECONDS = 2.0                # after a write failure, a new part is tried this often


class LogGap(BaseModel):
    """What a log lost while writes failed (a full disk): the first message of the part that resumed it."""

    model_config = {"title": "usv.LogGap"}

    dropped: int = Field(ge=0, description="messages not logged")
    topics: dict[str, int] = Field(description="of which, per topic")
    first_lost_ns: int | None = Field(description="log time of the first message lost")
    last_lost_ns: int | None = Field(description="log time of the last message lost")
    suspended_at: float = Field(description="wall-clock time (Unix s) of the failure")
    resumed_at: float = Field(description="wall-clock time (Unix s) the log resumed")
    error: str = Field(description="the write error that suspended the log")


class LogRotation(StrictModel):
    """How a long run's log is cut into parts, and how much of it is kept (McapLog's `rotation`).

    The defaults keep an agent (about 81 MB an hour) to 512 MB, the last six hours or so, in parts of 64 MB."""

    max_file_mb: PositiveFloat | None = Field(64.0, description="start a new part once the current one has this "
                                              "many MB (null: no size limit)")
    max_file_seconds: PositiveFloat | None = Field(None, description="start a new part once the current one is "
                                                   "this many seconds old (null: no time limit)")
    max_total_mb: PositiveFloat | None = Field(512.0, description="delete the oldest parts so that the set, the "
                                               "current part included, stays within this many MB (null: keep all)")

    @model_validator(mode="after")
    def _consistent(self) -> LogRotation:
        if self.max_file_mb is None and self.max_file_seconds is None:
            raise ValueError("give max_file_mb or max_file_seconds (or no rotation at all)")
        if self.max_total_mb is not None and self.max_file_mb is not None and self.max_total_mb < self.max_file_mb:
            raise ValueError(f"max_total_mb ({self.max_total_mb}) is less than one part (max_file_mb "
                             f"{self.max_file_mb})")
        return self


def part_path(first: str | Path, part: int) -> Path:
    """The file of part `part` of the log set whose first file is `first`: part 0 is `first` itself,
    part n is `<stem>.part<nnnn><suffix>`."""
    first = Path(first)
    if part == 0:
        return first
    return first.with_name(f"{first.stem}.part{part:0{PART_WIDTH}d}{first.suffix}")


class McapLog:
    """One process's log: `log()` messages, `close()` (or use it as a context manager).

    Counters: `errors` (OSErrors met while writing or closing), `dropped` (messages not written because the
    part they were for had failed), `deleted` (parts removed by `max_total_mb`). `parts` lists the files
    of the set written so far (deleted ones included), in order."""

    def __init__(self, path: str | Path, flush_seconds: float = 1.0, metadata: dict[str, str] | None = None,
                 rotation: LogRotation | None = None, retry_seconds: float = RETRY_SECONDS,
                 announce: Callable[[str], None] | None = None):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.rotation = rotation
        self.parts: list[Path] = []
        self.errors = 0
        self.dropped = 0
        self.deleted: list[Path] = []
        self.first_error: OSError | None = None
        self.close_error: OSError | None = None
        self._metadata = {k: str(v) for k, v in (metadata or {}).items()}
        self._set = uuid.uuid4().hex
        self._schemas: dict[str, tuple[str, dict]] = {}   # topic -> (schema name, JSON schema), for every part
        self._sequence: dict[str, int] = {}
        self._closed_sizes: list[tuple[Path, int]] = []   # closed parts still on disk, oldest first
        self._flush_seconds = flush_seconds
        self._retry_seconds = retry_seconds
        self._failed_at: float | None = None
        self._failing = False        # since the last write that reached the file, writes have failed
        self._open_error: OSError | None = None
        self._announce = announce
        self._gap: dict | None = None   # while suspended: what is lost (LogGap's fields so far)
        self._closed = False
        self._writer: Writer | None = None
        self._file = None
        self._open_part(0, raise_errors=True)

    # ----- parts -----
    def _open_part(self, part: int, raise_errors: bool = False) -> bool:
        """Start part `part`: its file, header and metadata records. False (counted) if that fails."""
        path = part_path(self.path, part)
        try:
            handle = path.open("wb")
        except OSError as error:
            if raise_errors:
                raise           # the first file: a path that cannot be opened at all is the caller's to see
            self._suspend(error)
            self._writer, self._failed_at, self._open_error = None, time.monotonic(), error
            return False
        self._file, self._part, self._channels = handle, part, {}
        self._opened = time.monotonic()
        self._last_flush = self._opened
        self.parts.append(path)
        try:
            self._writer = Writer(handle, compression=CompressionType.ZSTD)
            self._writer.start(profile=PROFILE, library="usv-circumnav")
            self._writer.add_metadata(FORMAT_RECORD, {"version": FORMAT_VERSION})
            if self._metadata:
                self._writer.add_metadata("run", self._metadata)
            self._writer.add_metadata(PART_RECORD, {"set": self._set, "part": str(part), "first": self.path.name})
        except OSError as error:
            self._abandon(error)
            self._open_error = error
            return False
        return True

    def _abandon(self, error: OSError) -> None:
        """The current part failed: count it, close its file as an unfinished log, write nothing more to it."""
        self._suspend(error)
        self._writer = None
        self._failed_at = time.monotonic()
        try:
            self._file.close()     # flushes what is buffered (which fails again on a full disk) and closes
        except OSError:
            pass
        size = self._size_on_disk(self.parts[-1])
        if not self._regular(self.parts[-1]):
            return          # a device (/dev/full) or the like: never deleted, its size means nothing
        if self._part > 0 and size == 0:
            # A part that failed before holding a byte (a retry on a still full disk) is no part at all: the
            # next try takes its number.
            self.parts[-1].unlink(missing_ok=True)
            self.parts.pop()
            self._part -= 1
        elif size == 0:
            # The first part, empty (the disk was full from the start): no file that no reader can read; the
            # set's later parts say it is missing.
            with contextlib.suppress(OSError):
                self.parts[-1].unlink(missing_ok=True)
        else:
            self._closed_sizes.append((self.parts[-1], size))   # kept, unfinished, and counted in the bound

    def _count(self, error: OSError) -> None:
        self.errors += 1
        if self.first_error is None:
            self.first_error = error

    def _suspend(self, error: OSError) -> None:
        """A write (or the start of a part) failed: count it; the first of a failure starts the gap record
        and is announced."""
        self._count(error)
        if self._gap is None:
            self._gap = {"dropped": 0, "topics": {}, "first_lost_ns": None, "last_lost_ns": None,
                         "suspended_at": time.time(), "error": f"{type(error).__name__}: {error}"}
            if self._announce is not None:
                where = self.parts[-1] if self.parts else self.path
                self._announce(f"{SUSPENDED}: {where}: {type(error).__name__}: {error}; messages are dropped "
                               f"and counted, and a new part is tried every {self._retry_seconds:g} s")

    @property
    def suspended(self) -> bool:
        """Writes have failed and no part has been opened since: messages are dropped."""
        return self._gap is not None and not self._closed

    def _drop(self, topic: str, log_time_ns: int) -> None:
        self.dropped += 1
        gap = self._gap
        if gap is not None:
            gap["dropped"] += 1
            gap["topics"][topic] = gap["topics"].get(topic, 0) + 1
            if gap["first_lost_ns"] is None:
                gap["first_lost_ns"] = log_time_ns
            gap["last_lost_ns"] = log_time_ns

    @staticmethod
    def _regular(path: Path) -> bool:
        try:
            return stat.S_ISREG(path.lstat().st_mode)
        except OSError:
            return False

    @staticmethod
    def _size_on_disk(path: Path) -> int:
        try:
            return path.stat().st_size
        except OSError:
            return 0

    def _due(self) -> bool:
        """The current part has reached a limit of the rotation."""
        rotation = self.rotation
        if rotation is None or self._writer is None:
            return False
        if rotation.max_file_mb is not None and self._file.tell() >= rotation.max_file_mb * MB:
            return True
        return rotation.max_file_seconds is not None and time.monotonic() - self._opened >= rotation.max_file_seconds

    def _rotate(self) -> None:
        """Finish the current part and start the next; then keep the set within its bound. An OSError while
        finishing is raised (log() abandons the part); one while starting the next leaves no writer."""
        path = self.parts[-1]
        self._writer.finish()
        self._file.close()
        self._closed_sizes.append((path, self._size_on_disk(path)))
        if self._open_part(self._part + 1):
            self._bound()

    def _bound(self) -> None:
        """Delete the oldest closed parts while they leave no room for a full current part in max_total_mb."""
        rotation = self.rotation
        if rotation is None or rotation.max_total_mb is None:
            return
        room = rotation.max_file_mb * MB if rotation.max_file_mb is not None else max(
            (size for _, size in self._closed_sizes[-1:]), default=0)
        while self._closed_sizes and sum(size for _, size in self._closed_sizes) + room > rotation.max_total_mb * MB:
            oldest, _ = self._closed_sizes.pop(0)
            try:
                oldest.unlink()
            except FileNotFoundError:
                pass
            except OSError as error:
                self._count(error)
                continue
            self.deleted.append(oldest)

    def _retry(self) -> bool:
        """After a failure: try a new part every retry_seconds. True if one is open now, its first message the
        gap record (LogGap) of what was lost."""
        if self._failed_at is None or (self.path.exists() and not self._regular(self.path)):
            return False    # a log written to a device (/dev/full in the tests) has no parts
        if time.monotonic() - self._failed_at < self._retry_seconds:
            return False
        self._failed_at = time.monotonic()
        if not self._open_part(self._part + 1):
            return False
        self._bound()
        gap = self._gap
        if gap is not None:
            record = LogGap(resumed_at=time.time(), **gap)
            try:
                self._write(GAP_TOPIC, record.model_dump_json().encode(), (record.last_lost_ns or 0),
                            "usv.LogGap", LogGap.model_json_schema())
                # To the file now: a part whose start fits in a buffer is not room until the disk took it.
                self._writer.flush()
                self._last_flush = time.monotonic()
            except OSError as error:     # still full: still suspended, the same gap goes on
                self._abandon(error)
                return False
            self._gap = None
            if self._announce is not None:
                self._announce(f"logging resumed in {self.parts[-1].name}: {gap['dropped']} message(s) lost "
                               f"in {time.time() - gap['suspended_at']:.1f} s (recorded on {GAP_TOPIC})")
        return True

    def _write(self, topic: str, data: bytes, log_time_ns: int, schema_name: str, schema: dict) -> None:
        self._schemas.setdefault(topic, (schema_name, schema))
        channel = self.channel(topic, *self._schemas[topic])
        self._writer.add_message(channel_id=channel, log_time=log_time_ns, publish_time=log_time_ns,
                                 data=data, sequence=self._sequence[topic])
        self._sequence[topic] += 1

    # ----- writing -----
    def channel(self, topic: str, schema_name: str, schema: dict) -> int:
        """The channel of `topic` in the current part, registering it with `schema` the first time."""
        self._schemas.setdefault(topic, (schema_name, schema))
        self._sequence.setdefault(topic, 0)
        if topic not in self._channels:
            name, body = self._schemas[topic]
            schema_id = self._writer.register_schema(name=name, encoding="jsonschema", data=json.dumps(body).encode())
            self._channels[topic] = self._writer.register_channel(topic=topic, message_encoding="json",
                                                                  schema_id=schema_id)
        return self._channels[topic]

    def prepare(self, topic: str, model: type[BaseModel]) -> None:
        """Make `topic`'s schema from `model` and register its channel now rather than with its first message:
        a JSON schema costs milliseconds to generate (17 ms of CPU for an agent's per-tick topics on a quiet
        machine), which a process pays at start-up instead of adding it to its first tick's answer."""
        if topic not in self._schemas:
            self._make_schema(topic, model, None)
        if self._writer is not None:
            self.channel(topic, *self._schemas[topic])

    def _make_schema(self, topic: str, source: dict | type[BaseModel] | None, schema_name: str | None) -> None:
        if isinstance(source, type) and issubclass(source, BaseModel):
            # A model's title is its class name unless it sets one (the Foxglove models do).
            body = source.model_json_schema()
            name = schema_name or body.get("title", source.__name__)
        else:
            name, body = schema_name or topic, source or {"type": "object"}
        self._schemas[topic] = (name, body)

    def log(self, topic: str, message: BaseModel | dict, log_time_ns: int, publish_time_ns: int | None = None,
            schema_name: str | None = None, schema: dict | type[BaseModel] | None = None,
            data: bytes | None = None) -> None:
        """Append one message; a pydantic message brings its own schema, a dict needs `schema` (a JSON schema,
        or the model whose dump the dict is). `data` is the message already encoded as JSON (what went on the
        wire), to save encoding it twice. Raises the OSError of a failed write once (module docstring)."""
        if self._closed:
            return
        if self._writer is None and not self._retry():
            self._drop(topic, log_time_ns)
            return
        model = isinstance(message, BaseModel)
        if data is None:
            # orjson: several times faster than json on these float-heavy dicts (logging cost as much CPU
            # as the tick itself); it writes floats exactly as json does, and NaN or infinity as null.
            data = message.model_dump_json().encode() if model else orjson.dumps(message, option=NUMPY)
        if topic not in self._schemas:  # a schema is made once per topic: generating one costs milliseconds
            self._make_schema(topic, type(message) if model and schema is None else schema, schema_name)
        try:
            if self._due():
                self._rotate()
                if self._writer is None:       # the next part could not be started
                    raise self._open_error
            channel = self.channel(topic, *self._schemas[topic])
            self._writer.add_message(channel_id=channel, log_time=log_time_ns,
                                     publish_time=publish_time_ns if publish_time_ns is not None else log_time_ns,
                                     data=data, sequence=self._sequence[topic])
            self._sequence[topic] += 1
            now = time.monotonic()
            if now - self._last_flush >= self._flush_seconds:
                self._last_flush = now
                self._writer.flush()
                self._failing = False          # it reached the file: a later failure is news again
        except OSError as error:
            if self._writer is not None:
                self._abandon(error)
            self._drop(topic, log_time_ns)
            first, self._failing = not self._failing, True
            if first and self._announce is None:   # once per failure, not once per message or per retry
                raise

    def close(self) -> None:
        """Write the summary and footer and close the file; safe to call twice. An OSError (a full disk) is
        not raised: the file is closed all the same, as an unfinished log, the error kept in `close_error`,
        and one line on stderr says what the log lost (so does any earlier write error)."""
        if self._closed:
            return
        self._closed = True
        unfinished = self._writer is None     # its last part was abandoned after a write error
        if self._writer is not None:
            try:
                self._writer.finish()
            except OSError as error:
                self.close_error = error
                self._count(error)
            try:
                self._file.close()
            except OSError as error:
                self.close_error = self.close_error or error
                self._count(error)
            self._writer = None
            unfinished = self.close_error is not None
        if self.errors:
            error = self.first_error
            print(f"mcap log {self.path}: {self.errors} write error(s) ({type(error).__name__}: {error}); "
                  f"{self.dropped} message(s) not logged; "
                  + ("its last part is unfinished (read up to its last complete chunk)" if unfinished
                     else "its last part is complete"), file=sys.stderr)

    def __enter__(self) -> McapLog:
        return self

    def __exit__(self, kind, error, traceback) -> None:
        self.close()
        if error is not None and self.close_error is not None:
            # The exception that ended the block is the one to see; the log's failure goes with it.
            failure = self.close_error
            note = f"and closing the log {self.path} failed: {type(failure).__name__}: {failure}"
            if hasattr(error, "add_note"):
                error.add_note(note)
            else:                       # Python 3.10: no notes on exceptions
                print(note, file=sys.stderr)


def read_messages(path: str | Path) -> Iterator[tuple[str, int, dict]]:
    """(topic, log_time_ns, decoded JSON) of every message, in file order. A file cut short (a process killed
    hard) is read up to its last complete record, with a warning."""
    channels: dict[int, str] = {}
    with Path(path).open("rb") as handle:
        reader = StreamReader(handle, skip_magic=False)
        try:
            for record in reader.records:
                if isinstance(record, Channel):
                    channels[record.id] = record.topic
                elif isinstance(record, Message):
                    yield channels.get(record.channel_id, "?"), record.log_time, orjson.loads(record.data)
        except (McapError, EOFError, ValueError, struct.error) as error:   # struct: cut inside a record header
            warnings.warn(f"{path}: unfinished MCAP, read up to the last complete record ({error})",
                          stacklevel=2)


def read_metadata(path: str | Path) -> dict[str, dict[str, str]]:
    """The metadata records of a log (name -> key -> value); they are written first, so an unfinished file
    has them too."""
    found: dict[str, dict[str, str]] = {}
    with Path(path).open("rb") as handle:
        try:
            for record in StreamReader(handle, skip_magic=False).records:
                if isinstance(record, Metadata):
                    found[record.name] = dict(record.metadata)
        except (McapError, EOFError, ValueError, struct.error):
            pass  # read_messages warns about an unfinished file; the metadata before the cut is all there
    return found
