"""Merge part files into one MCAP: messages by log time, schemas shared by name, channels by
(topic, schema), with the run's metadata and attachments; written to a temporary name and
renamed, so the output is never half written."""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from mcap.writer import Writer

from nodes.recording.errors import RecordingError
from nodes.recording.parts import COMPRESSION, LIBRARY, PROFILE, check_compression, read_part

#: Chunk size of the merged file (mcap's default; readers seek by chunk).
MERGED_CHUNK_BYTES = 1024 * 1024


@dataclass(frozen=True)
class Attachment:
    name: str
    media_type: str
    data: bytes
    create_time_ns: int = 0


@dataclass
class MergeReport:
    """What `merge` wrote: per-topic message counts and each part's state."""

    path: Path
    counts: dict[str, int]
    parts: dict[str, dict[str, Any]]

    @property
    def messages(self) -> int:
        return sum(self.counts.values())


def merge(
    parts: Sequence[Path],
    out: Path,
    compression: str = "zstd",
    metadata: dict[str, dict[str, str]] | None = None,
    attachments: Sequence[Attachment] = (),
) -> MergeReport:
    """Merge part files into one MCAP at `out`, messages ordered by log time (ties keep part
    order, then sequence). Schemas are shared by name, channels by (topic, schema). The file
    is written to a temporary name and renamed, so `out` is never half written."""
    check_compression(compression)
    contents = [read_part(p) for p in parts]
    tmp = out.with_name(f".{out.name}.tmp")
    counts: dict[str, int] = {}
    with open(tmp, "wb") as f:
        writer = Writer(f, chunk_size=MERGED_CHUNK_BYTES, compression=COMPRESSION[compression])
        writer.start(profile=PROFILE, library=LIBRARY)
        schema_ids: dict[str, int] = {}
        schema_data: dict[str, bytes] = {}
        channel_ids: dict[tuple[str, str], int] = {}
        mapped: list[dict[int, int]] = []  # per part: its channel id -> merged channel id
        for part in contents:
            ids: dict[int, int] = {}
            for cid, ch in part.channels.items():
                schema = part.schemas.get(ch.schema_id)
                if schema is None:
                    raise RecordingError(f"{part.path}: channel {ch.topic} has no schema")
                if schema.name not in schema_ids:
                    schema_ids[schema.name] = writer.register_schema(
                        schema.name, schema.encoding, schema.data
                    )
                    schema_data[schema.name] = schema.data
                elif schema_data[schema.name] != schema.data:
                    raise RecordingError(
                        f"{part.path}: type {schema.name} has a different definition than in "
                        "another part (mixed interface builds in one run)"
                    )
                key = (ch.topic, schema.name)
                if key not in channel_ids:
                    channel_ids[key] = writer.register_channel(
                        ch.topic, ch.message_encoding, schema_ids[schema.name], dict(ch.metadata)
                    )
                ids[cid] = channel_ids[key]
            mapped.append(ids)
        order = sorted(
            (m.log_time, i, m.sequence, j)
            for i, part in enumerate(contents)
            for j, m in enumerate(part.messages)
        )
        topic_of = {cid: topic for (topic, _), cid in channel_ids.items()}
        sequence: dict[int, int] = {}
        for _, i, _, j in order:
            m = contents[i].messages[j]
            cid = mapped[i][m.channel_id]
            seq = sequence.get(cid, 0)
            sequence[cid] = seq + 1
            writer.add_message(cid, m.log_time, m.data, m.publish_time, sequence=seq)
            counts[topic_of[cid]] = counts.get(topic_of[cid], 0) + 1
        for name, values in (metadata or {}).items():
            writer.add_metadata(name, values)
        for a in attachments:
            writer.add_attachment(a.create_time_ns, time.time_ns(), a.name, a.media_type, a.data)
        writer.finish()
    tmp.replace(out)
    report_parts = {
        p.path.name: {
            "messages": len(p.messages),
            "complete": p.complete,
            **({"problem": p.problem} if p.problem else {}),
        }
        for p in contents
    }
    return MergeReport(out, counts, report_parts)
