"""CRC-64 of OpenIGTLink bodies (ECMA-182: polynomial 0x42F0E1EBA9EA3693,
most significant bit first, initial value and final XOR 0), eight bytes a
step (slicing-by-8), compiled, the GIL released: every frame's body is
checked as it is read, and the receiving thread must not hold up the
tracking one."""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["crc64"]

POLYNOMIAL = 0x42F0E1EBA9EA3693


def _tables() -> np.ndarray:
    """``T[k][b]``: the CRC of byte ``b`` followed by ``k`` zero bytes."""
    tables = np.zeros((8, 256), dtype=np.uint64)
    for b in range(256):
        c = b << 56
        for _ in range(8):
            c = ((c << 1) ^ POLYNOMIAL) if c & (1 << 63) else (c << 1)
            c &= (1 << 64) - 1
        tables[0, b] = c
    for k in range(1, 8):
        for b in range(256):
            previous = int(tables[k - 1, b])
            tables[k, b] = ((previous << 8) & ((1 << 64) - 1)) ^ int(tables[0, previous >> 56])
    return tables


_TABLES = _tables()


@numba.njit(cache=True, nogil=True)
def _crc64(data, tables):
    crc = np.uint64(0)
    n = data.shape[0]
    blocks = n // 8
    eight = np.uint64(8)
    mask = np.uint64(0xFF)
    for b in range(blocks):
        i = 8 * b
        word = np.uint64(0)
        for k in range(8):
            word = (word << eight) | np.uint64(data[i + k])
        x = crc ^ word
        crc = (tables[7, (x >> np.uint64(56)) & mask] ^ tables[6, (x >> np.uint64(48)) & mask]
               ^ tables[5, (x >> np.uint64(40)) & mask] ^ tables[4, (x >> np.uint64(32)) & mask]
               ^ tables[3, (x >> np.uint64(24)) & mask] ^ tables[2, (x >> np.uint64(16)) & mask]
               ^ tables[1, (x >> eight) & mask] ^ tables[0, x & mask])
    for i in range(8 * blocks, n):
        crc = tables[0, ((crc >> np.uint64(56)) ^ np.uint64(data[i])) & mask] ^ (crc << eight)
    return crc


def crc64(data) -> int:
    """The CRC-64 of ``data`` (bytes-like)."""
    return int(_crc64(np.frombuffer(data, dtype=np.uint8), _TABLES))
