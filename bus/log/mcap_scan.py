"""Low-level, defensive MCAP record parsing for :mod:`bus.log.reader`.

Every function takes a buffer (``bytes`` or an ``mmap``) and explicit bounds and raises
:class:`Corrupt` instead of reading past a record or trusting a broken length.
"""

from __future__ import annotations

import struct
import zlib
from collections.abc import Iterator
from typing import Any

MAGIC = b"\x89MCAP0\r\n"
SCHEMA, CHANNEL, MESSAGE, CHUNK = 0x03, 0x04, 0x05, 0x06
FOOTER, STATISTICS, METADATA, DATA_END = 0x02, 0x0B, 0x0C, 0x0F
MAX_OP = 0x0F
U16, U32, U64 = struct.Struct("<H"), struct.Struct("<I"), struct.Struct("<Q")
_MAX_CHUNK = 1 << 34


class Corrupt(Exception):
    """A record that does not parse or check out."""


def num(fmt: struct.Struct, buf: Any, off: int, end: int) -> tuple[int, int]:
    """(value, next offset) of a fixed-size integer at ``off``."""
    if off + fmt.size > end:
        raise Corrupt("record too short")
    return fmt.unpack_from(buf, off)[0], off + fmt.size


def string(buf: Any, off: int, end: int) -> tuple[str, int]:
    """(text, next offset) of a uint32-length-prefixed UTF-8 string."""
    n, off = num(U32, buf, off, end)
    if off + n > end:
        raise Corrupt("string runs past its record")
    try:
        return bytes(buf[off:off + n]).decode("utf-8"), off + n
    except UnicodeDecodeError as err:
        raise Corrupt(str(err)) from None


def string_map(buf: Any, off: int, end: int) -> tuple[dict[str, str], int]:
    """(dict, next offset) of a uint32-byte-length-prefixed string->string map."""
    n, off = num(U32, buf, off, end)
    stop = off + n
    if stop > end:
        raise Corrupt("map runs past its record")
    out = {}
    while off < stop:
        k, off = string(buf, off, stop)
        out[k], off = string(buf, off, stop)
    return out, stop


def chunk_records(buf: Any, off: int, end: int) -> bytes:
    """Chunk record body -> uncompressed, CRC-checked records."""
    off += 16  # message start and end times
    size, off = num(U64, buf, off, end)
    crc, off = num(U32, buf, off, end)
    compression, off = string(buf, off, end)
    clen, off = num(U64, buf, off, end)
    if off + clen != end or size > _MAX_CHUNK:
        raise Corrupt("chunk sizes do not add up")
    raw: bytes = buf[off:end]  # a copy: nothing keeps the file's mmap exported
    try:
        if compression == "zstd":
            import zstandard

            raw = zstandard.ZstdDecompressor().decompress(raw, max_output_size=size)
        elif compression == "lz4":
            import lz4.frame

            raw = lz4.frame.decompress(raw)
        elif compression:
            raise Corrupt(f"unknown chunk compression {compression!r}")
    except Corrupt:
        raise
    except Exception as err:  # noqa: BLE001 - any decompressor error is corruption
        raise Corrupt(f"chunk does not decompress: {err}") from None
    if len(raw) != size or (crc and zlib.crc32(raw) != crc):
        raise Corrupt("chunk CRC or size mismatch")
    return raw


def records(buf: Any, off: int, end: int) -> Iterator[tuple[int, int, int]]:
    """(opcode, body start, body end) of the records in ``buf[off:end]``; raises
    ``Corrupt`` on a record that runs past ``end``."""
    while off < end:
        if off + 9 > end:
            raise Corrupt("record header cut")
        op = buf[off]
        n = U64.unpack_from(buf, off + 1)[0]
        body = off + 9
        if body + n > end:
            raise Corrupt("record runs past the end")
        yield op, body, body + n
        off = body + n


def resync(buf: Any, off: int, end: int) -> int | None:
    """Offset of the next chunk or metadata record that fully checks out."""
    nxt = {b"\x06": buf.find(b"\x06", off, end), b"\x0c": buf.find(b"\x0c", off, end)}
    while True:
        live = [(h, op) for op, h in nxt.items() if h >= 0]
        if not live:
            return None
        pos, op = min(live)
        nxt[op] = buf.find(op, pos + 1, end)  # each byte is searched once
        if pos + 9 <= end:
            stop = pos + 9 + U64.unpack_from(buf, pos + 1)[0]
            if stop <= end:
                try:
                    if buf[pos] == CHUNK:
                        raw = chunk_records(buf, pos + 9, stop)
                        for _ in records(raw, 0, len(raw)):
                            pass
                    else:
                        name, o = string(buf, pos + 9, stop)
                        if string_map(buf, o, stop)[1] != stop or not name.startswith(
                                ("skyloop.", "rosbag2")):
                            raise Corrupt("not ours")
                    return pos
                except Corrupt:
                    pass
