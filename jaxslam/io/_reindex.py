"""Rebuild the index of a ROS1 bag whose recording was cut (power loss, a killed recorder).

A ROS1 v2.0 bag is a header, chunks (compressed groups of connection and message records) and,
written last, an index. Without the index (never closed, or the file cut short) readers refuse
the bag; the chunks before the cut are intact. :func:`reindex` walks the chunks sequentially
and writes a new bag with their connections and messages, dropping (and counting) a cut or
malformed tail. ``python -m drivers.record reindex BAG`` and ``jaxslam run`` use it.
"""

from __future__ import annotations

import bz2
import os
import struct
from collections import Counter
from pathlib import Path
from typing import Any, BinaryIO

from rosbags.rosbag1 import Writer
from rosbags.typesys.msg import normalize_msgtype

from ..errors import ConfigError, InputFormatError

_OP_MSGDATA, _OP_BAGHEADER, _OP_IDXDATA, _OP_CHUNK, _OP_CHUNK_INFO, _OP_CONNECTION = 2, 3, 4, 5, 6, 7
_U32 = struct.Struct("<I")


def _fields(header: bytes) -> dict[str, bytes]:
    out: dict[str, bytes] = {}
    pos = 0
    while pos + 4 <= len(header):
        (n,) = _U32.unpack_from(header, pos)
        field = header[pos + 4 : pos + 4 + n]
        if len(field) != n or b"=" not in field:
            raise ValueError("malformed record header")
        name, _, value = field.partition(b"=")
        out[name.decode("ascii", "replace")] = value
        pos += 4 + n
    return out


def _records(buf: BinaryIO | bytes, stats: Counter[str]) -> Any:
    """Yield ``(fields, data)`` records from a file object (from its position) or bytes; a
    truncated or malformed record ends the iteration (counted in ``stats``)."""
    read = buf.read if not isinstance(buf, bytes) else None
    pos = 0

    def take(n: int) -> bytes:
        nonlocal pos
        if read is not None:
            return read(n)
        chunk = buf[pos : pos + n]  # type: ignore[index]
        pos += len(chunk)
        return chunk

    while True:
        raw = take(4)
        if not raw:
            return
        if len(raw) < 4:
            stats["truncated_records"] += 1
            return
        (hlen,) = _U32.unpack(raw)
        header = take(hlen) if hlen < 1 << 20 else b""
        raw = take(4) if len(header) == hlen else b""
        if len(raw) < 4:
            stats["truncated_records"] += 1
            return
        (dlen,) = _U32.unpack(raw)
        data = take(dlen)
        if len(data) < dlen:
            stats["truncated_records"] += 1
            return
        try:
            fields = _fields(header)
        except ValueError:
            stats["malformed_records"] += 1
            return
        yield fields, data


def _decompress(kind: bytes, data: bytes) -> bytes:
    if kind == b"none":
        return data
    if kind == b"bz2":
        return bz2.decompress(data)
    if kind == b"lz4":
        import lz4.frame  # rosbags depends on lz4

        return lz4.frame.decompress(data)
    raise ValueError(f"unknown chunk compression {kind!r}")


def reindex(src: str | Path, dst: str | Path | None = None) -> dict[str, int]:
    """Rebuild a ROS1 bag from its chunks (a recorder killed before writing the index).

    ``dst`` None: repair in place, keeping the original as ``<name>.orig.bag``. Returns
    counts: ``connections``, ``messages``, ``chunks``, and ``truncated_records`` /
    ``malformed_records`` / ``bad_chunks`` for what was dropped. Raises InputFormatError when
    ``src`` is not a ROS1 v2.0 bag.
    """
    src = Path(src)
    in_place = dst is None
    out = src.with_name(src.stem + ".reindex-tmp.bag") if dst is None else Path(dst)
    if out.exists():
        raise ConfigError(f"{out} exists; not overwriting")
    stats: Counter[str] = Counter(connections=0, messages=0, chunks=0)
    try:
        f = open(src, "rb")  # noqa: SIM115 - closed below
    except OSError as exc:
        raise InputFormatError(f"cannot open bag: {exc}", src) from None
    writer = Writer(out)
    writer.open()
    conns: dict[int, Any] = {}
    by_key: dict[tuple, Any] = {}
    try:
        if f.read(13) != b"#ROSBAG V2.0\n":
            raise InputFormatError("not a ROS1 v2.0 bag (no '#ROSBAG V2.0' line)", src)
        for fields, data in _records(f, stats):
            if fields.get("op", b"\x00")[:1] != bytes([_OP_CHUNK]):
                continue  # bag header, index data, connection / chunk-info index records
            try:
                inner = _decompress(fields.get("compression", b"none"), data)
            except (ValueError, OSError, EOFError, RuntimeError):
                stats["bad_chunks"] += 1
                continue
            stats["chunks"] += 1
            for ifields, idata in _records(inner, stats):
                op = ifields.get("op", b"\x00")[:1]
                try:
                    if op == bytes([_OP_CONNECTION]):
                        cid = _U32.unpack(ifields["conn"][:4])[0]
                        c = _fields(idata)
                        key = (ifields["topic"], c["type"], c["md5sum"], c.get("message_definition", b""))
                        if key not in by_key:
                            by_key[key] = writer.add_connection(
                                ifields["topic"].decode(),
                                normalize_msgtype(c["type"].decode()),
                                msgdef=c.get("message_definition", b"").decode(),
                                md5sum=c["md5sum"].decode(),
                                callerid=c["callerid"].decode() if "callerid" in c else None,
                                latching=int(c["latching"]) if "latching" in c else None,
                            )
                            stats["connections"] += 1
                        conns[cid] = by_key[key]
                    elif op == bytes([_OP_MSGDATA]):
                        cid = _U32.unpack(ifields["conn"][:4])[0]
                        sec, nsec = struct.unpack("<II", ifields["time"][:8])
                        if cid not in conns:
                            stats["messages_without_connection"] += 1
                            continue
                        writer.write(conns[cid], sec * 10**9 + nsec, idata)
                        stats["messages"] += 1
                except (KeyError, ValueError, struct.error, UnicodeDecodeError):
                    stats["malformed_records"] += 1
        writer.close()
    except BaseException:
        writer.abort()
        out.unlink(missing_ok=True)
        raise
    finally:
        f.close()
    if in_place:
        backup = src.with_name(src.stem + ".orig.bag")
        if backup.exists():
            out.unlink()
            raise ConfigError(f"{backup} exists; remove it or pass -o")
        os.replace(src, backup)
        os.replace(out, src)
    return dict(stats)
