"""A damage-tolerant index of an MCAP file and its messages in log-time order.

The ``mcap`` package reads well-formed files; a recording cut short by a full disk or a
copy that stopped, or one with flipped bytes, makes it raise somewhere inside its
iterators, or (a damaged summary) read the wrong bytes. This module finds out where a file
is damaged and reads everything before that point:

* A file with an intact summary section (its footer is there and the summary's CRC holds)
  is indexed from the summary: chunk indexes, channels, schemas, attachment and metadata
  indexes, statistics. Opening costs a few reads, whatever the file's size.
* Otherwise (truncated file, damaged summary, no summary) the data section is scanned
  record by record, reading only each chunk's header, never its contents; the scan stops
  at the first record that runs past the end of the file or makes no sense, and that
  point is remembered as :attr:`McapIndex.damage`. Channels and schemas inside chunks are
  then discovered as the chunks are read.

:meth:`McapIndex.messages` yields the messages from a start time in log-time order (chunks
are merged by their time ranges, as the ``mcap`` reader does), checking every chunk's CRC;
the first unreadable chunk, or the end of a truncated file, raises :class:`McapDamage`
after every message before it in time was yielded.

Nothing a file declares is trusted with memory or time: a chunk (compressed, or as it
declares itself uncompressed) larger than :data:`MAX_CHUNK_BYTES` is damage before any of
it is read; it is decompressed into at most its declared size (zstd's and lz4's own frame
headers are not believed) and must come out exactly that long; its records are walked by
this module, and anything but schemas, channels and messages in it (e.g. a run of zero
bytes) is damage, not skipped. An exception about damage holds no reference to the
chunk's bytes.
"""

from __future__ import annotations

import heapq
import io
import os
import struct
import zlib
from collections.abc import Collection, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import lz4.frame
import numpy as np
import zstandard
from mcap.data_stream import ReadDataStream
from mcap.exceptions import EndOfFile
from mcap.opcode import Opcode
from mcap.records import (
    Attachment,
    AttachmentIndex,
    Channel,
    ChunkIndex,
    Message,
    MessageIndex,
    Metadata,
    MetadataIndex,
    Schema,
    Statistics,
)

from trifuse.app.errors import describe_error
from trifuse.app.recording.errors import RecordingError
from trifuse.app.recording.layout import METADATA_NAME as SEALED_BY

MAGIC = b"\x89MCAP0\r\n"
_PREFIX = 9  # opcode (1) + record length (8)
_FOOTER_LENGTH = 20  # summary_start (8) + summary_offset_start (8) + summary_crc (4)
_FOOTER_SIZE = _PREFIX + _FOOTER_LENGTH
_KNOWN_OPCODES = {int(op) for op in Opcode}
_COMPRESSIONS = ("", "zstd", "lz4")
_UNFINISHED = 2**64 - 1  # the record length a streaming writer puts first, then fixes
MAX_CHUNK_BYTES = 64 * 2**20
"""The most a chunk may hold, compressed and uncompressed (bytes of its records); so may a
message outside chunks. A larger one is damage, found before it is read. trifuse's writer
ends a chunk once it passes ``chunk_size`` (1 MiB by default, at most 16 MiB: see
:data:`app.recording.writer.MAX_CHUNK_SIZE`) and refuses a rig whose frames could make a
message over :data:`app.recording.writer.MAX_MESSAGE_BYTES` (a 1280 x 960 JPEG is about
0.3 MB, a raw 16-bit 382 x 288 thermal frame 0.2 MB); rosbag2 ends its chunks at 768 KiB.
Reading a chunk of this size costs about three times it in memory (the record, its
decompressed records, the messages)."""
MAX_CHUNK_RECORDS = 200_000
"""The most records a chunk may hold, and at most one per byte it takes in the file (plus
:data:`RECORDS_FLOOR`): a chunk of millions of identical tiny messages, a few kilobytes
compressed, would cost seconds of CPU and hundreds of MB of message objects each. A
legitimate chunk holds far fewer: trifuse's densest (16 MiB of head poses) about 130,000,
rosbag2's 768 KiB at most about 25,000; real messages take several bytes each compressed."""
RECORDS_FLOOR = 4096
"""Records any chunk may hold, whatever its size in the file."""
ATTACHMENT_LIMIT = 64 * 2**20
"""The largest attachment or metadata record read, bytes (the default limit of
:meth:`McapIndex.attachment`)."""
_CHUNK_HEAD = struct.Struct("<QQQII")  # start, end, uncompressed size and CRC, compression
_MESSAGE_HEAD = struct.Struct("<HIQQ")  # channel id, sequence, log time, publish time
_CHUNK_RECORDS = (Opcode.SCHEMA, Opcode.CHANNEL, Opcode.MESSAGE)


class _Corrupt(ValueError):
    """What is wrong inside one chunk (becomes a McapDamage outside any except block)."""


class McapDamage(Exception):
    """The file cannot be read past this point (internal; the sources turn it into
    :class:`~app.recording.errors.RecordingDamaged`)."""

    def __init__(self, reason: str, offset: int | None, stamp_ns: int | None = None) -> None:
        super().__init__(reason)
        self.reason = reason
        self.offset = offset
        self.stamp_ns = stamp_ns


@dataclass(frozen=True)
class ChunkRef:
    """Where a chunk (or a message outside chunks) is, and the log times it covers.

    Attributes:
        offset: byte offset of the record (its opcode).
        length: the record's content length (after the 9-byte prefix).
        start_ns, end_ns: log time of its first and last message.
        message: for a message written outside any chunk, the message itself.
        message_index_offsets: channel id -> offset of the chunk's message index record
            for that channel (from the summary's chunk index; empty when scanned).
    """

    offset: int
    length: int
    start_ns: int
    end_ns: int
    message: Message | None = None
    message_index_offsets: dict[int, int] = field(default_factory=dict)


@dataclass
class McapIndex:
    """What is known about an MCAP file after opening it (see the module docstring).

    Attributes:
        path: the file.
        size: its size in bytes.
        library: the writer's library string from the header ("" if unreadable).
        profile: the header's profile ("ros2", "" ...).
        schemas, channels: by id; grows as chunks are read when the file was scanned.
        chunks: the chunks (and loose messages) sorted by offset.
        attachments: name -> attachment index (offset, length ...).
        metadata: name -> key/value strings.
        message_counts: channel id -> message count, from the statistics (None if scanned).
        indexed_by: "summary" or "scan".
        notes: non-fatal problems found while opening (e.g. a damaged summary section).
        damage: where the scan stopped early (truncation, garbage), else None: the data
            after it is lost.
    """

    path: Path
    size: int
    library: str = ""
    profile: str = ""
    schemas: dict[int, Schema] = field(default_factory=dict)
    channels: dict[int, Channel] = field(default_factory=dict)
    chunks: list[ChunkRef] = field(default_factory=list)
    attachments: dict[str, AttachmentIndex] = field(default_factory=dict)
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    message_counts: dict[int, int] | None = None
    indexed_by: str = "summary"
    notes: list[str] = field(default_factory=list)
    damage: McapDamage | None = None
    _file: io.BufferedReader | None = field(default=None, repr=False)

    # -- opening --------------------------------------------------------------------------

    @classmethod
    def open(cls, path: str | Path) -> McapIndex:
        """Open and index ``path``; RecordingError if it is no MCAP file at all."""
        path = Path(path)
        try:
            f = path.open("rb")
        except OSError as exc:
            raise RecordingError(f"{path}: cannot open recording: {exc.strerror}") from None
        try:
            size = os.fstat(f.fileno()).st_size
            head = f.read(len(MAGIC))
            if head != MAGIC:
                raise RecordingError(
                    f"{path}: not an MCAP file (expected the MCAP magic bytes at the start, "
                    f"got {head!r})"
                )
            index = cls(path=path, size=size, _file=f)
            index._read_header()
            reason = index._read_summary()
            if reason is not None:
                if reason != "no summary":
                    index.notes.append(f"{reason}; the file was indexed by scanning it instead")
                index.indexed_by = "scan"
                index._scan()
                if reason == "no summary" and index.damage is None and SEALED_BY in index.metadata:
                    # trifuse writes a summary when it finishes a recording: without one, the
                    # file is what its writer had sealed when it stopped
                    index.damage = McapDamage(
                        "the recording was not finished: its writer stopped or was killed "
                        "(it holds what was sealed up to about a second before)",
                        index.size,
                    )
            return index
        except BaseException:
            f.close()
            raise

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None

    @property
    def file(self) -> io.BufferedReader:
        if self._file is None:
            raise RecordingError(f"{self.path}: the recording is closed")
        return self._file

    def _read_at(self, offset: int, n: int) -> bytes:
        f = self.file
        f.seek(offset)
        return f.read(n)

    def _record_at(self, offset: int, limit: int | None = None) -> tuple[int, bytes]:
        """(opcode, content) of the record at ``offset``; McapDamage if it is cut short or
        its content is longer than ``limit`` bytes (then nothing of it is read)."""
        prefix = self._read_at(offset, _PREFIX)
        if len(prefix) < _PREFIX:
            raise McapDamage("the file ends inside a record's header: truncated", offset)
        opcode, length = struct.unpack("<BQ", prefix)
        if limit is not None and length > limit:
            raise McapDamage(
                f"a record of {length} bytes, more than the {limit} bytes one may have here: "
                "corrupted",
                offset,
            )
        if offset + _PREFIX + length > self.size:
            raise McapDamage(
                f"a record of {length} bytes runs past the end of the file: truncated or corrupted",
                offset,
            )
        content = self.file.read(length)
        if len(content) < length:
            raise McapDamage("the file ends inside a record: truncated", offset)
        return opcode, content

    def _read_header(self) -> None:
        try:
            opcode, content = self._record_at(len(MAGIC))
            if opcode == Opcode.HEADER:
                stream = ReadDataStream(io.BytesIO(content))
                self.profile = stream.read_prefixed_string()
                self.library = stream.read_prefixed_string()
        except Exception:  # a damaged header does not stop the rest from being read
            self.notes.append("the header record is damaged")

    def _read_summary(self) -> str | None:
        """Index from the summary section; returns why it could not (None: done)."""
        if self.size < len(MAGIC) * 2 + _FOOTER_SIZE:
            return "the file is too short to hold a footer (truncated?)"
        tail = self._read_at(self.size - len(MAGIC) - _FOOTER_SIZE, _FOOTER_SIZE + len(MAGIC))
        if tail[-len(MAGIC) :] != MAGIC:
            return "the file does not end with the MCAP magic bytes (truncated?)"
        opcode, length, summary_start, _summary_offset_start, summary_crc = struct.unpack(
            "<BQQQI", tail[:_FOOTER_SIZE]
        )
        if opcode != Opcode.FOOTER or length != _FOOTER_LENGTH:
            return "the footer record is damaged"
        footer_offset = self.size - len(MAGIC) - _FOOTER_SIZE
        if summary_start == 0:
            return "no summary"
        if not len(MAGIC) < summary_start <= footer_offset:
            return "the footer points outside the file"
        # The CRC covers the summary section and the footer up to (excluding) the CRC.
        covered = self._read_at(summary_start, self.size - len(MAGIC) - 4 - summary_start)
        if summary_crc != 0 and zlib.crc32(covered) != summary_crc:
            return "the summary section is damaged (CRC mismatch)"
        try:
            self._parse_summary(covered[: footer_offset - summary_start])
        except Exception as exc:
            self.schemas.clear()
            self.channels.clear()
            self.chunks.clear()
            self.attachments.clear()
            self.metadata.clear()
            return f"the summary section cannot be parsed ({exc})"
        if not self.chunks and self.message_counts and sum(self.message_counts.values()):
            # messages outside chunks: only a scan finds them
            self.schemas.clear()
            self.channels.clear()
            self.attachments.clear()
            self.metadata.clear()
            return "no summary"
        return None

    def _register(self, opcode: int, stream: ReadDataStream) -> bool:
        """Keep a schema or channel record; False for any other kind of record."""
        if opcode == Opcode.SCHEMA:
            schema = Schema.read(stream)
            self.schemas[schema.id] = schema
        elif opcode == Opcode.CHANNEL:
            channel = Channel.read(stream)
            self.channels[channel.id] = channel
        else:
            return False
        return True

    def _parse_summary(self, data: bytes) -> None:
        pos = 0
        metadata_indexes: list[MetadataIndex] = []
        while pos < len(data):
            opcode, length = struct.unpack_from("<BQ", data, pos)
            content = data[pos + _PREFIX : pos + _PREFIX + length]
            if len(content) != length:
                raise ValueError(f"record at summary byte {pos} is cut short")
            stream = ReadDataStream(io.BytesIO(content))
            if self._register(opcode, stream):
                pass
            elif opcode == Opcode.CHUNK_INDEX:
                ci = ChunkIndex.read(stream)
                if ci.chunk_start_offset + ci.chunk_length > self.size:
                    raise ValueError("a chunk index points past the end of the file")
                self.chunks.append(
                    ChunkRef(
                        ci.chunk_start_offset,
                        ci.chunk_length - _PREFIX,
                        ci.message_start_time,
                        ci.message_end_time,
                        message_index_offsets=dict(ci.message_index_offsets),
                    )
                )
            elif opcode == Opcode.ATTACHMENT_INDEX:
                ai = AttachmentIndex.read(stream)
                self.attachments.setdefault(ai.name, ai)
            elif opcode == Opcode.METADATA_INDEX:
                metadata_indexes.append(MetadataIndex.read(stream))
            elif opcode == Opcode.STATISTICS:
                st = Statistics.read(stream)
                self.message_counts = dict(st.channel_message_counts)
            pos += _PREFIX + length
        self.chunks.sort(key=lambda c: c.offset)
        for mi in metadata_indexes:
            opcode, content = self._record_at(mi.offset, ATTACHMENT_LIMIT)
            if opcode != Opcode.METADATA:
                raise ValueError(f"metadata index points at a record of type {opcode}")
            md = Metadata.read(ReadDataStream(io.BytesIO(content)))
            self.metadata.setdefault(md.name, dict(md.metadata))

    def _scan(self) -> None:
        """Walk the data section's records (chunk headers only) up to the first damage."""
        pos = len(MAGIC)
        while True:
            if pos == self.size:
                self.damage = McapDamage(
                    "the file ends without its footer (truncated after a complete record)", pos
                )
                return
            prefix = self._read_at(pos, _PREFIX)
            if len(prefix) < _PREFIX:
                self.damage = McapDamage("the file ends inside a record's header: truncated", pos)
                return
            opcode, length = struct.unpack("<BQ", prefix)
            if opcode not in _KNOWN_OPCODES:
                self.damage = McapDamage(
                    f"unknown record type 0x{opcode:02x}: the file is corrupted from here on",
                    pos,
                )
                return
            end = pos + _PREFIX + length
            if end > self.size:
                name = Opcode(opcode).name.lower().replace("_", " ")
                article = "an" if name[0] in "aeiou" else "a"
                if length == _UNFINISHED:  # a writer's placeholder until the record is done
                    what = (
                        f"{article} {name} record that was still being written "
                        f"({self.size - pos - _PREFIX} bytes of it present): the recording "
                        "was not finished (truncated: its writer stopped or was killed)"
                    )
                else:
                    what = (
                        f"{article} {name} record ({self.size - pos - _PREFIX} of "
                        f"{length} bytes present): truncated"
                    )
                self.damage = McapDamage(f"the file ends inside {what}", pos)
                return
            try:
                stop = self._scan_record(pos, opcode, length)
            except McapDamage as exc:
                self.damage = exc
                return
            except Exception as exc:
                name = Opcode(opcode).name.lower()
                self.damage = McapDamage(f"damaged {name} record ({exc})", pos)
                return
            if stop:
                return
            pos = end

    def _scan_record(self, pos: int, opcode: int, length: int) -> bool:
        """Index one record found by the scan; True at the end of the data section."""
        if opcode in (Opcode.DATA_END, Opcode.FOOTER):
            return True
        if opcode == Opcode.CHUNK:
            head = self.file.read(min(length, 8 + 8 + 8 + 4 + 4))
            start, end, _size, _crc, clen = struct.unpack("<QQQII", head)
            compression = self.file.read(min(clen, 16)).decode("utf-8", "replace")
            if compression not in _COMPRESSIONS or start > end:
                raise McapDamage(
                    f"chunk header makes no sense (compression {compression!r}, times "
                    f"{start}..{end}): corrupted",
                    pos,
                )
            self.chunks.append(ChunkRef(pos, length, start, end))
            return False
        if opcode in (Opcode.SCHEMA, Opcode.CHANNEL, Opcode.MESSAGE, Opcode.METADATA):
            if length > MAX_CHUNK_BYTES:
                raise McapDamage(
                    f"a {Opcode(opcode).name.lower()} record of {length} bytes, more than "
                    f"{MAX_CHUNK_BYTES // 2**20} MiB: corrupted",
                    pos,
                )
            content = self.file.read(length)
            stream = ReadDataStream(io.BytesIO(content))
            if self._register(opcode, stream):
                pass
            elif opcode == Opcode.MESSAGE:
                m = Message.read(stream, length)
                self.chunks.append(ChunkRef(pos, length, m.log_time, m.log_time, m))
            else:
                md = Metadata.read(stream)
                self.metadata.setdefault(md.name, dict(md.metadata))
            return False
        if opcode == Opcode.ATTACHMENT:
            head = self.file.read(min(length, 16 + 4))
            log_time, create_time, name_len = struct.unpack("<QQI", head)
            name = self.file.read(name_len).decode("utf-8")
            (mt_len,) = struct.unpack("<I", self.file.read(4))
            media_type = self.file.read(mt_len).decode("utf-8")
            (data_size,) = struct.unpack("<Q", self.file.read(8))
            index = AttachmentIndex(
                pos, length + _PREFIX, log_time, create_time, data_size, name, media_type
            )
            self.attachments.setdefault(name, index)
            return False
        return False  # message indexes and anything else in the data section: skipped

    # -- reading --------------------------------------------------------------------------

    @property
    def start_ns(self) -> int | None:
        """Log time of the first message, None if there are none."""
        return min((c.start_ns for c in self.chunks), default=None)

    @property
    def end_ns(self) -> int | None:
        """Log time of the last message, None if there are none."""
        return max((c.end_ns for c in self.chunks), default=None)

    def attachment(self, name: str, limit: int = ATTACHMENT_LIMIT) -> bytes | None:
        """The data of the attachment ``name`` (None if absent); McapDamage if its CRC or
        its record is damaged, or the record is longer than ``limit`` bytes."""
        ai = self.attachments.get(name)
        if ai is None:
            return None
        opcode, content = self._record_at(ai.offset, limit)
        if opcode != Opcode.ATTACHMENT:
            raise McapDamage(f"attachment {name!r}: no attachment record there", ai.offset)
        if len(content) < 4:
            raise McapDamage(f"attachment {name!r}: the record is cut short", ai.offset)
        (crc,) = struct.unpack("<I", content[-4:])
        if crc != 0 and zlib.crc32(content[:-4]) != crc:
            raise McapDamage(f"attachment {name!r}: CRC mismatch", ai.offset)
        try:  # without a CRC, damage shows only here
            att = Attachment.read(ReadDataStream(io.BytesIO(content)))
        except (EndOfFile, struct.error, UnicodeDecodeError) as exc:
            raise McapDamage(
                f"attachment {name!r}: the record is damaged ({type(exc).__name__})", ai.offset
            ) from None
        return att.data

    def read_chunk(self, ref: ChunkRef) -> list[Message]:
        """The messages of one chunk (or the loose message); learns its schemas and
        channels. McapDamage when the chunk cannot be read, is larger than
        :data:`MAX_CHUNK_BYTES`, fails its CRC or holds anything but schemas, channels and
        messages (see the module docstring)."""
        if ref.message is not None:
            self._check_channel(ref.message, ref)
            return [ref.message]
        problem = None
        try:
            messages = self._chunk_messages(ref)
        except _Corrupt as exc:
            problem = str(exc)
        if problem is not None:  # raised here, so that nothing keeps the chunk's bytes
            raise McapDamage(
                f"chunk of messages at {ref.start_ns / 1e9:.3f}-{ref.end_ns / 1e9:.3f} s "
                f"(log time) {problem}",
                ref.offset,
                ref.start_ns,
            )
        for m in messages:
            self._check_channel(m, ref)
        return messages

    def _chunk_messages(self, ref: ChunkRef) -> list[Message]:
        """Read, check and decompress one chunk record; _Corrupt says what is wrong."""
        cap = MAX_CHUNK_BYTES
        if ref.length > cap + 4096:  # its header, then at most the cap of records
            raise _Corrupt(
                f"is a record of {ref.length} bytes, more than a chunk may hold "
                f"({cap // 2**20} MiB): corrupted"
            )
        opcode, content = self._record_at(ref.offset, ref.length)
        if opcode != Opcode.CHUNK or len(content) != ref.length:
            raise _Corrupt("is not where the index says: the file is corrupted")
        if len(content) < _CHUNK_HEAD.size:
            raise _Corrupt("is cut short: corrupted")
        _start, _end, size, crc, name_len = _CHUNK_HEAD.unpack_from(content)
        at = _CHUNK_HEAD.size + name_len
        if at + 8 > len(content):
            raise _Corrupt("has a damaged header: corrupted")
        compression = content[_CHUNK_HEAD.size : at].decode("utf-8", "replace")
        (records_len,) = struct.unpack_from("<Q", content, at)
        if records_len > len(content) - at - 8:
            raise _Corrupt(f"claims {records_len} bytes of records, more than its record holds")
        if size > cap:
            raise _Corrupt(
                f"declares {size} bytes of records uncompressed, more than a chunk may hold "
                f"({cap // 2**20} MiB): corrupted"
            )
        data = _decompress(compression, memoryview(content)[at + 8 : at + 8 + records_len], size)
        del content
        if crc != 0 and zlib.crc32(data) != crc:
            raise _Corrupt("fails its CRC: corrupted")
        return self._chunk_records(data, min(MAX_CHUNK_RECORDS, RECORDS_FLOOR + records_len))

    def _chunk_records(self, data: bytes, most: int) -> list[Message]:
        """The messages among a chunk's decompressed records (schemas and channels are
        learnt); _Corrupt at any other record, one that runs past the end, or more than
        ``most`` records."""
        out: list[Message] = []
        pos, n, count = 0, len(data), 0
        while pos < n:
            count += 1
            if count > most:
                raise _Corrupt(
                    f"holds more than {most} records (a chunk may hold {RECORDS_FLOOR} plus "
                    f"one per byte it takes in the file, at most {MAX_CHUNK_RECORDS}): "
                    "corrupted or hostile"
                )
            if n - pos < _PREFIX:
                raise _Corrupt("ends inside a record's header: corrupted")
            opcode, length = struct.unpack_from("<BQ", data, pos)
            start, pos = pos + _PREFIX, pos + _PREFIX + length
            if pos > n:
                raise _Corrupt(f"holds a record of {length} bytes that runs past its end")
            if opcode not in _CHUNK_RECORDS:
                raise _Corrupt(
                    f"holds a record of type 0x{opcode:02x} (a chunk holds schemas, channels "
                    "and messages only): corrupted"
                )
            if opcode == Opcode.MESSAGE:
                if length < _MESSAGE_HEAD.size:
                    raise _Corrupt(f"holds a message record of {length} bytes: corrupted")
                channel_id, sequence, log_time, publish_time = _MESSAGE_HEAD.unpack_from(
                    data, start
                )
                body = data[start + _MESSAGE_HEAD.size : pos]
                out.append(Message(channel_id, log_time, body, publish_time, sequence))
                continue
            try:
                stream = ReadDataStream(io.BytesIO(data[start:pos]))
                if opcode == Opcode.SCHEMA:
                    schema = Schema.read(stream)
                    self.schemas.setdefault(schema.id, schema)
                else:
                    channel = Channel.read(stream)
                    self.channels.setdefault(channel.id, channel)
            except (EndOfFile, struct.error, UnicodeDecodeError) as exc:
                raise _Corrupt(
                    f"holds a damaged schema or channel ({type(exc).__name__})"
                ) from None
        return out

    def _check_channel(self, message: Message, ref: ChunkRef) -> None:
        if message.channel_id not in self.channels:
            raise McapDamage(
                f"a message refers to channel {message.channel_id}, which the file never "
                "defines: corrupted",
                ref.offset,
                message.log_time,
            )

    def log_times(self, channel_ids: Collection[int]) -> np.ndarray | None:
        """(N,) int64 sorted log times (ns) of every message on ``channel_ids``, read from
        the chunks' message indexes (a few small reads per chunk, no chunk is
        decompressed); None when the file has no such index (it was scanned, or its writer
        wrote none) or an index record is damaged."""
        wanted = set(channel_ids)
        if self.indexed_by != "summary" or self.message_counts is None:
            return None
        times: list[int] = []
        for c in self.chunks:
            if c.message is not None:
                return None
            for cid, offset in c.message_index_offsets.items():
                if cid not in wanted:
                    continue
                try:
                    opcode, content = self._record_at(offset)
                    if opcode != Opcode.MESSAGE_INDEX:
                        return None
                    index = MessageIndex.read(ReadDataStream(io.BytesIO(content)))
                except (McapDamage, EndOfFile, struct.error):
                    return None
                times += [t for t, _ in index.records]
        expected = sum(self.message_counts.get(cid, 0) for cid in wanted)
        if len(times) != expected:
            return None  # some chunks carry no index of the channel
        return np.sort(np.asarray(times, dtype=np.int64))

    def schema_of(self, channel: Channel) -> Schema | None:
        return self.schemas.get(channel.schema_id) if channel.schema_id else None

    def messages(self, start_ns: int | None = None) -> Iterator[Message]:
        """Messages with log time >= ``start_ns`` in log-time order (ties: file order).

        Raises McapDamage at the first unreadable chunk (every message earlier in log time
        than that chunk's first message was yielded), or at the end when the scan found the
        file truncated or corrupted.
        """
        heap: list[tuple[int, int, int, object]] = []
        for c in self.chunks:
            if start_ns is None or c.end_ns >= start_ns:
                heap.append((c.start_ns, c.offset, -1, c))
        heapq.heapify(heap)
        last = None
        while heap:
            t, offset, i, item = heapq.heappop(heap)
            if i < 0:
                assert isinstance(item, ChunkRef)
                try:
                    msgs = self.read_chunk(item)
                except McapDamage as exc:
                    exc.stamp_ns = last
                    raise
                for k, m in enumerate(msgs):
                    if start_ns is None or m.log_time >= start_ns:
                        heapq.heappush(heap, (m.log_time, offset, k, m))
                continue
            assert isinstance(item, Message)
            last = t
            yield item
        if self.damage is not None:
            raise McapDamage(self.damage.reason, self.damage.offset, last)


def _decompress(compression: str, data: memoryview, size: int) -> bytes:
    """A chunk's records, decompressed into at most ``size`` (its declared uncompressed
    size) bytes and exactly that many; _Corrupt otherwise."""
    if compression not in _COMPRESSIONS:
        raise _Corrupt(f"has an unknown compression {compression!r}: corrupted")
    try:
        if compression == "zstd":
            declared = zstandard.frame_content_size(data)
            if declared not in (size, -1):  # -1: the frame does not say
                raise _Corrupt(f"holds a zstd frame of {declared} bytes, but declares {size}")
            out = zstandard.ZstdDecompressor().decompress(data, max_output_size=size)
        elif compression == "lz4":
            out = lz4.frame.LZ4FrameDecompressor().decompress(data, max_length=size + 1)
        else:
            out = bytes(data)
    except (zstandard.ZstdError, RuntimeError) as exc:
        raise _Corrupt(f"cannot be decompressed ({describe_error(exc)}): corrupted") from None
    if len(out) != size:
        more = "more than " if len(out) > size else ""
        raise _Corrupt(
            f"decompresses to {more}{min(len(out), size)} bytes, but declares {size}: corrupted"
        )
    return out
