"""Part files: each process records what it publishes into its own MCAP, `parts/<process>.mcap`.

A part is written in small chunks, flushed at least every `PART_FLUSH_S`, so a process killed
with SIGKILL leaves a file that `read_part` reads up to its last complete chunk. Writing happens
on a background thread: a publisher only pays for serialising and a queue put.
"""

from __future__ import annotations

import contextlib
import importlib.metadata
import queue
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO

from mcap.exceptions import McapError
from mcap.records import Channel, Message, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from nodes.recording.errors import RecordingError
from nodes.recording.schemas import full_type_name, schema_text

PROFILE = "ros2"
MESSAGE_ENCODING = "cdr"
SCHEMA_ENCODING = "ros2msg"


def _library() -> str:
    try:
        return f"edgeloc-testbed {importlib.metadata.version('edgeloc-testbed')}"
    except importlib.metadata.PackageNotFoundError:  # a checkout that was never installed
        return "edgeloc-testbed"


LIBRARY = _library()
#: Uncompressed bytes per chunk of a part: small, so a killed writer loses little.
PART_CHUNK_BYTES = 64 * 1024
#: A part's open chunk is written out at least this often (a quiet topic is not held back).
PART_FLUSH_S = 1.0

COMPRESSION = {
    "zstd": CompressionType.ZSTD,
    "lz4": CompressionType.LZ4,
    "none": CompressionType.NONE,
}


def check_compression(compression: str) -> None:
    if compression not in COMPRESSION:
        raise RecordingError(f"compression {compression!r}: use one of {', '.join(COMPRESSION)}")


class PartWriter:
    """One process's part file: messages given as CDR bytes, written by a background thread.

    `write` only queues (the caller may be a real-time thread); the thread registers each
    topic's schema and channel the first time it sees it, adds messages to the current chunk,
    and writes the chunk out when it is full or `flush_s` old. `close` drains the queue and
    writes the summary. If writing fails, the next `write` raises `RecordingError` with why
    (a node then fails loudly instead of recording nothing).
    """

    def __init__(
        self,
        path: Path,
        compression: str = "lz4",
        chunk_bytes: int = PART_CHUNK_BYTES,
        flush_s: float = PART_FLUSH_S,
        search: Sequence[Path] | None = None,
    ) -> None:
        check_compression(compression)
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.flush_s = flush_s
        self.search = search
        self.counts: dict[str, int] = {}  # messages queued per topic
        self.error: str | None = None
        self._file: IO[bytes] = open(self.path, "wb")  # noqa: SIM115 (closed by the thread)
        self._writer = Writer(
            self._file, chunk_size=chunk_bytes, compression=COMPRESSION[compression]
        )
        self._writer.start(profile=PROFILE, library=LIBRARY)
        self._channels: dict[tuple[str, str], int] = {}
        self._schemas: dict[str, int] = {}
        self._sequence: dict[int, int] = {}
        self._queue: queue.SimpleQueue[tuple[str, str, bytes, int, int] | None] = (
            queue.SimpleQueue()
        )
        self._closed = False
        self._thread = threading.Thread(target=self._run, name="mcap-part", daemon=True)
        self._thread.start()

    def write(
        self, topic: str, type_name: str, data: bytes, log_time_ns: int | None = None
    ) -> None:
        """Queue one message (CDR bytes of `type_name`) on `topic`, logged now by default."""
        if self.error is not None:
            raise RecordingError(f"recording to {self.path} failed: {self.error}")
        if self._closed:
            raise RecordingError(f"recording to {self.path} is closed")
        t = time.time_ns() if log_time_ns is None else log_time_ns
        self.counts[topic] = self.counts.get(topic, 0) + 1
        self._queue.put((topic, type_name, data, t, t))

    def close(self) -> None:
        """Write what is queued and the summary; idempotent. Raises if writing failed."""
        if not self._closed:
            self._closed = True
            self._queue.put(None)
            self._thread.join()
        if self.error is not None:
            raise RecordingError(f"recording to {self.path} failed: {self.error}")

    # -- the writer thread -----------------------------------------------------------------

    def _channel(self, topic: str, type_name: str) -> int:
        key = (topic, type_name)
        if key not in self._channels:
            if type_name not in self._schemas:
                text = schema_text(type_name, self.search)
                self._schemas[type_name] = self._writer.register_schema(
                    full_type_name(type_name), SCHEMA_ENCODING, text.encode()
                )
            self._channels[key] = self._writer.register_channel(
                topic, MESSAGE_ENCODING, self._schemas[type_name]
            )
        return self._channels[key]

    def _run(self) -> None:
        pending_since: float | None = None  # when the open chunk got its first message
        try:
            while True:
                timeout = None
                if pending_since is not None:
                    timeout = max(0.0, pending_since + self.flush_s - time.monotonic())
                try:
                    item = self._queue.get(timeout=timeout)
                except queue.Empty:
                    item = ()  # the open chunk is due
                if item is None:
                    break
                if item:
                    topic, type_name, data, log_time, publish_time = item
                    cid = self._channel(topic, type_name)
                    seq = self._sequence.get(cid, 0)
                    self._sequence[cid] = seq + 1
                    self._writer.add_message(cid, log_time, data, publish_time, sequence=seq)
                    if pending_since is None:
                        pending_since = time.monotonic()
                if pending_since is not None and time.monotonic() - pending_since >= self.flush_s:
                    self._writer.flush()  # ends the chunk: readable if we are killed now
                    pending_since = None
            self._writer.finish()
        except Exception as err:  # reported by write/close: a node must not record silently
            self.error = f"{type(err).__name__}: {err}"
        finally:
            # A full disk fails this close too; the first error is the one `error` keeps.
            with contextlib.suppress(OSError):
                self._file.close()


@dataclass
class PartContents:
    """What `read_part` recovered from one part file."""

    path: Path
    schemas: dict[int, Schema] = field(default_factory=dict)
    channels: dict[int, Channel] = field(default_factory=dict)
    messages: list[Message] = field(default_factory=list)
    complete: bool = False  # the file ended with its footer (the writer closed it)
    problem: str = ""  # why reading stopped early, when it did


def read_part(path: Path) -> PartContents:
    """Every schema, channel and message of a part, up to its last complete chunk.

    Reads records in file order (no index needed), so a file cut anywhere, e.g. by SIGKILL
    in the middle of a chunk, yields everything before that chunk; `problem` says where it
    stopped and `complete` whether the file was closed properly.
    """
    out = PartContents(Path(path))
    with open(path, "rb") as f:
        reader = StreamReader(f, skip_magic=False, emit_chunks=False, validate_crcs=True)
        try:
            for record in reader.records:
                if isinstance(record, Schema):
                    out.schemas[record.id] = record
                elif isinstance(record, Channel):
                    out.channels[record.id] = record
                elif isinstance(record, Message):
                    out.messages.append(record)
            out.complete = True
        except (McapError, EOFError, ValueError, OSError) as err:
            out.problem = f"{type(err).__name__}: {err}" if str(err) else type(err).__name__
        except Exception as err:  # a torn chunk can fail inside the decompressor
            out.problem = f"{type(err).__name__}: {err}"
    # A message whose channel was lost with a torn chunk cannot be decoded: drop it.
    out.messages = [m for m in out.messages if m.channel_id in out.channels]
    return out
