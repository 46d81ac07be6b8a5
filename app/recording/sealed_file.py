"""A file for the MCAP writer that is a complete, readable MCAP at every moment.

foxglove-sdk's writer streams a chunk record with a placeholder length (2**64 - 1) and
patches it when the chunk ends, and keeps the summary and footer for ``close()``: a
recording killed half-way held only its header, or a record no reader gets past. The writer
accepts any file-like object with ``write``, ``seek`` and ``flush``; :class:`SealedMcapFile`
is one that keeps everything after the last complete record in memory and puts on disk only
complete records, each time followed by a *seal*: a ``DataEnd`` record, a ``Footer`` without
summary and the closing magic. Every flush (:meth:`flush`, called by the writer's own
``flush()``, which first finishes the chunk in progress) writes the new records and a new
seal, in an order that keeps the file valid if the process is killed in the middle of a
write (:meth:`flush`), so a reader always finds a valid MCAP, without a summary, holding
everything up to the last flush. :meth:`finish` writes the writer's real ending (summary,
footer) instead.

Record framing (MCAP spec): after the 8-byte magic, records of opcode (1 byte), length
(uint64 little-endian) and that many bytes.
"""

from __future__ import annotations

import os
import struct
from pathlib import Path

MAGIC = b"\x89MCAP0\r\n"
_DATA_END = 0x0F
_FOOTER = 0x02
_UNKNOWN_LENGTH = 2**64 - 1


def _record(opcode: int, body: bytes) -> bytes:
    return struct.pack("<BQ", opcode, len(body)) + body


SEAL = (
    _record(_DATA_END, struct.pack("<I", 0))  # data section CRC 0: not computed
    + _record(_FOOTER, struct.pack("<QQI", 0, 0, 0))  # no summary section
    + MAGIC
)
"""What ends the file between flushes: DataEnd, a Footer without summary, the magic."""


class SealedMcapFile:
    """A binary file object for ``foxglove.open_mcap`` (see the module docstring).

    Args:
        path: the file to create (it must not exist).
        sync: ``fdatasync`` after every flush (the data also survives a power cut).
    """

    def __init__(self, path: str | Path, sync: bool = True) -> None:
        self.path = Path(path)
        self.fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_EXCL, 0o666)
        self.sync = sync
        self.committed = 0  # logical bytes on disk (complete records), the seal after them
        self.pending = bytearray()  # logical bytes from ``committed`` on
        self.pos = 0
        self.closed = False

    # -- the file protocol the writer uses ------------------------------------------------

    def write(self, data: bytes) -> int:
        data, n = bytes(data), len(data)
        if self.pos < self.committed:  # a patch of what is on disk already (the writer
            k = min(n, self.committed - self.pos)  # patches only the record in progress;
            os.pwrite(self.fd, data[:k], self.pos)  # kept correct anyway)
            data, self.pos = data[k:], self.pos + k
        offset = self.pos - self.committed
        end = offset + len(data)
        if end > len(self.pending):
            self.pending.extend(bytes(end - len(self.pending)))
        self.pending[offset:end] = data
        self.pos += len(data)
        return n

    def seek(self, offset: int, whence: int = 0) -> int:
        base = {0: 0, 1: self.pos, 2: self.committed + len(self.pending)}[whence]
        self.pos = base + offset
        if self.pos < 0:
            raise ValueError(f"seek before the start of {self.path}")
        return self.pos

    def tell(self) -> int:
        return self.pos

    def flush(self) -> None:
        """Put the complete records received so far on disk, sealed.

        A SIGKILL can cut a large ``pwrite`` short (Linux stops copying at a page boundary
        when a fatal signal is pending), so the new records never overwrite the old seal
        until they are on disk: first the new seal at the new end of the file, then the
        records after the old seal (meanwhile a reader's linear scan from the start still
        stops at the old seal's footer, whatever lies behind it), and last the records'
        first ``len(SEAL)`` bytes over the old seal, one small write.
        """
        n = self._complete_prefix()
        if not n:
            return
        new = bytes(self.pending[:n])
        head = len(SEAL)
        if self.committed == 0 or n <= head:  # nothing sealed yet, or a write of a few bytes
            os.pwrite(self.fd, new + SEAL, self.committed)
        else:
            os.pwrite(self.fd, SEAL, self.committed + n)
            os.pwrite(self.fd, new[head:], self.committed + head)
            if self.sync:
                os.fdatasync(self.fd)  # the same order on disk after a power cut
            os.pwrite(self.fd, new[:head], self.committed)
        del self.pending[:n]
        self.committed += n
        if self.sync:
            os.fdatasync(self.fd)

    # -- the end ---------------------------------------------------------------------------

    def finish(self) -> None:
        """After the writer's ``close()``: write its ending (summary, footer, magic) over
        the seal, cut the file there and sync it (the descriptor stays open: :meth:`close`)."""
        os.pwrite(self.fd, bytes(self.pending), self.committed)
        self.committed += len(self.pending)
        self.pending.clear()
        os.ftruncate(self.fd, self.committed)
        os.fsync(self.fd)

    def close(self) -> None:
        """Close the descriptor (what is on disk stays: a sealed MCAP)."""
        if not self.closed:
            self.closed = True
            os.close(self.fd)

    def _complete_prefix(self) -> int:
        """How many bytes at the start of ``pending`` are whole records (or the magic)."""
        buf, n = self.pending, 0
        if self.committed == 0:
            if len(buf) < len(MAGIC):
                return 0
            n = len(MAGIC)
        while len(buf) - n >= 9:
            _opcode, length = struct.unpack_from("<BQ", buf, n)
            if length == _UNKNOWN_LENGTH or len(buf) - n - 9 < length:
                break
            n += 9 + length
        return n if n > (len(MAGIC) if self.committed == 0 else 0) else 0
