"""CRC-64 of OpenIGTLink bodies (ECMA-182: polynomial 0x42F0E1EBA9EA3693,
most significant bit first, initial value and final XOR 0): compiled with
the package (:mod:`spheroseg._compiled._crc`), the plain-Python reference
where it is not built."""

from __future__ import annotations

__all__ = ["POLYNOMIAL", "crc64", "crc64_reference"]

POLYNOMIAL = 0x42F0E1EBA9EA3693
_MASK = (1 << 64) - 1


def _table() -> list[int]:
    """``T[b]``: the CRC of the byte ``b``."""
    table = []
    for b in range(256):
        c = b << 56
        for _ in range(8):
            c = (((c << 1) ^ POLYNOMIAL) if c & (1 << 63) else (c << 1)) & _MASK
        table.append(c)
    return table


_TABLE = _table()


def crc64_reference(data) -> int:
    """The CRC-64 of ``data`` (bytes-like), a byte at a time: the definition
    the compiled kernel is tested equal to."""
    crc = 0
    for byte in bytes(data):
        crc = _TABLE[((crc >> 56) ^ byte) & 0xFF] ^ ((crc << 8) & _MASK)
    return crc


def crc64(data) -> int:
    """The CRC-64 of ``data`` (bytes-like)."""
    try:
        from ..._compiled._crc import crc64 as compiled
    except ImportError:  # a source tree without the build: the reference
        return crc64_reference(data)
    return compiled(memoryview(data).cast("B"))
