"""Hostile files for the hardening tests: zip archives written by hand, deflate bombs that are never
inflated here, and a peak-memory probe in a fresh interpreter."""

from __future__ import annotations

import io
import struct
import subprocess
import sys
import zlib

GIB = 1 << 30


def write_zip(path, members):
    """A zip archive: members are (name, bytes) stored, or (name, (raw deflate stream, crc, uncompressed
    size)) deflated as given (a bomb is written without inflating it)."""
    out, central = io.BytesIO(), []
    for name, data in members:
        if isinstance(data, bytes):
            method, raw, crc, usize = 0, data, zlib.crc32(data), len(data)
        else:
            method, (raw, crc, usize) = 8, data
        offset = out.tell()
        out.write(struct.pack("<IHHHHHIIIHH", 0x04034B50, 20, 0, method, 0, 0, crc, len(raw), usize,
                              len(name), 0) + name.encode() + raw)
        central.append(struct.pack("<IHHHHHHIIIHHHHHII", 0x02014B50, 20, 20, 0, method, 0, 0, crc,
                                   len(raw), usize, len(name), 0, 0, 0, 0, 0, offset) + name.encode())
    start = out.tell()
    for c in central:
        out.write(c)
    out.write(struct.pack("<IHHHHIIH", 0x06054B50, 0, 0, len(central), len(central), out.tell() - start,
                          start, 0))
    path.write_bytes(out.getvalue())
    return path


def zeros_bomb(size: int, prefix: bytes = b"") -> tuple[bytes, int, int]:
    """(raw deflate stream, crc, uncompressed size) of `prefix` then `size` zero bytes (a multiple of 1 MiB)
    in a few kB, never inflated: full-flush segments are independent, so one 1 MiB segment repeats. The
    CRC is not computed (0): a reader that inflated everything would fail only at the end."""
    head = zlib.compressobj(9, zlib.DEFLATED, -15)
    first = head.compress(prefix) + head.flush(zlib.Z_FULL_FLUSH) if prefix else b""
    seg = zlib.compressobj(9, zlib.DEFLATED, -15)
    one = seg.compress(bytes(1 << 20)) + seg.flush(zlib.Z_FULL_FLUSH)
    return first + one * (size >> 20) + zlib.compressobj(9, zlib.DEFLATED, -15).flush(), 0, len(prefix) + size


def peak_mb(code: str) -> tuple[int, str]:
    """Run `code` in a fresh interpreter -> (its peak resident memory in MB, its last printed line).

    The peak is /proc/self/status's VmHWM (this process image's own high-water mark), not getrusage's
    ru_maxrss: Linux carries ru_maxrss across fork and exec, so a child of a large test process (pytest
    after hundreds of tests) would report the parent's size."""
    probe = ("\nimport re\n"
             "print(int(re.search(r'VmHWM:\\s+(\\d+)', open('/proc/self/status').read())[1]) // 1024)")
    run = subprocess.run([sys.executable, "-c", code + probe],
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    lines = run.stdout.strip().splitlines()
    return int(lines[-1]), lines[-2]
