"""MCAP logs: what a process received, published and decided, as JSON with JSON schemas.

Each topic gets a channel whose schema is the JSON schema of the pydantic model logged on it (or one given),
so a file opens in Foxglove and every field can be plotted. The chunk in progress is written out at least
every `flush_seconds` of wall time: a process killed hard loses at most about that much, and
`read_messages` reads an unfinished file up to its last complete chunk.

Every file records its log format in a metadata record `usv-log-format` (`version`), written first with
the `run` metadata: a reader checks it before reading on (mission_log/reader.py). A message's JSON may gain
fields within a version; a change an older reader would misread needs a new version.
"""

from __future__ import annotations

import json
import time
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Self

import orjson
from mcap.exceptions import McapError
from mcap.stream_reader import Channel, Message, Metadata, StreamReader
from mcap.writer import CompressionType, Writer
from pydantic import BaseModel

PROFILE = ""  # plain JSON messages, no ROS profile
NUMPY = orjson.OPT_SERIALIZE_NUMPY
FORMAT_RECORD = "usv-log-format"   # metadata record: {"version": FORMAT_VERSION}
FORMAT_VERSION = "2"               # 2: inputs carry range_stamp. The channels of agent/runtime/log_schema.py, the `run` metadata


class McapLog:
    def __init__(self, path: str | Path, flush_seconds: float = 1.0, metadata: dict[str, str] | None = None):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file = self.path.open("wb")
        self._writer = Writer(self._file, compression=CompressionType.ZSTD)
        self._writer.start(profile=PROFILE, library="usv-circumnav")
        self._writer.add_metadata(FORMAT_RECORD, {"version": FORMAT_VERSION})
        if metadata:
            self._writer.add_metadata("run", {k: str(v) for k, v in metadata.items()})
        self._channels: dict[str, int] = {}
        self._sequence: dict[str, int] = {}
        self._flush_seconds = flush_seconds
        self._last_flush = time.monotonic()
        self._closed = False

    def channel(self, topic: str, schema_name: str, schema: dict) -> int:
        """The channel of `topic`, registering it with `schema` the first time."""
        if topic not in self._channels:
            schema_id = self._writer.register_schema(name=schema_name, encoding="jsonschema",
                                                     data=json.dumps(schema).encode())
            self._channels[topic] = self._writer.register_channel(topic=topic, message_encoding="json",
                                                                  schema_id=schema_id)
            self._sequence[topic] = 0
        return self._channels[topic]

    def log(self, topic: str, message: BaseModel | dict, log_time_ns: int, publish_time_ns: int | None = None,
            schema_name: str | None = None, schema: dict | type[BaseModel] | None = None,
            data: bytes | None = None) -> None:
        """Append one message; a pydantic message brings its own schema, a dict needs `schema` (a JSON schema,
        or the model whose dump the dict is). `data` is the message already encoded as JSON (what went on the
        wire), to save encoding it twice."""
        if self._closed:
            return
        model = isinstance(message, BaseModel)
        if data is None:
            # orjson: several times faster than json on these float-heavy dicts (logging cost as much CPU
            # as the tick itself); it writes floats exactly as json does, and NaN or infinity as null.
            data = message.model_dump_json().encode() if model else orjson.dumps(message, option=NUMPY)
        channel = self._channels.get(topic)
        if channel is None:  # a schema is made once per topic: generating one costs milliseconds
            source = type(message) if model and schema is None else schema
            if isinstance(source, type) and issubclass(source, BaseModel):
                # A model's title is its class name unless it sets one (the Foxglove models do).
                body = source.model_json_schema()
                name = schema_name or body.get("title", source.__name__)
            else:
                name, body = schema_name or topic, source or {"type": "object"}
            channel = self.channel(topic, name, body)
        self._writer.add_message(channel_id=channel, log_time=log_time_ns,
                                 publish_time=publish_time_ns if publish_time_ns is not None else log_time_ns,
                                 data=data, sequence=self._sequence[topic])
        self._sequence[topic] += 1
        now = time.monotonic()
        if now - self._last_flush >= self._flush_seconds:
            self._writer.flush()
            self._last_flush = now

    def close(self) -> None:
        """Write the summary and footer and close the file; safe to call twice. If writing fails (a full disk)
        the file is closed all the same, as an unfinished log, and the error raised; a second call does
        nothing."""
        if self._closed:
            return
        self._closed = True
        try:
            self._writer.finish()
        finally:
            self._file.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, kind, error, traceback) -> None:
        try:
            self.close()
        except Exception as failure:
            if error is None:
                raise
            # The exception that ended the block is the one to see; the log's failure goes with it.
            error.add_note(f"and closing the log {self.path} failed: {type(failure).__name__}: {failure}")


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
        except (McapError, EOFError, ValueError) as error:
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
        except (McapError, EOFError, ValueError):
            pass  # read_messages warns about an unfinished file; the metadata before the cut is all there
    return found
