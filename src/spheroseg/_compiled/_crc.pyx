# cython: language_level=3, boundscheck=False, wraparound=False
"""CRC-64 of OpenIGTLink bodies (ECMA-182: polynomial 0x42F0E1EBA9EA3693,
most significant bit first, initial value and final XOR 0), eight bytes a
step (slicing-by-8), the GIL released: every frame's body is checked as it
is read, and the receiving thread must not hold up the tracking one.  The
reference is :func:`spheroseg.apps.live.crc.crc64_reference`."""

from libc.stdint cimport uint8_t, uint64_t

cdef uint64_t POLYNOMIAL = 0x42F0E1EBA9EA3693ULL
# T[k][b]: the CRC of byte b followed by k zero bytes
cdef uint64_t TABLES[8][256]


cdef void _fill() noexcept nogil:
    cdef int b, k, bit
    cdef uint64_t c
    for b in range(256):
        c = (<uint64_t> b) << 56
        for bit in range(8):
            c = ((c << 1) ^ POLYNOMIAL) if c & (1ULL << 63) else (c << 1)
        TABLES[0][b] = c
    for k in range(1, 8):
        for b in range(256):
            TABLES[k][b] = (TABLES[k - 1][b] << 8) ^ TABLES[0][TABLES[k - 1][b] >> 56]


_fill()


def crc64(const uint8_t[::1] data):
    """The CRC-64 of ``data`` (a contiguous byte buffer), as an int."""
    cdef Py_ssize_t n = data.shape[0], blocks = n // 8, b, i, k
    cdef uint64_t crc = 0, word, x
    with nogil:
        for b in range(blocks):
            i = 8 * b
            word = 0
            for k in range(8):
                word = (word << 8) | data[i + k]
            x = crc ^ word
            crc = (TABLES[7][(x >> 56) & 0xFF] ^ TABLES[6][(x >> 48) & 0xFF] ^ TABLES[5][(x >> 40) & 0xFF]
                   ^ TABLES[4][(x >> 32) & 0xFF] ^ TABLES[3][(x >> 24) & 0xFF] ^ TABLES[2][(x >> 16) & 0xFF]
                   ^ TABLES[1][(x >> 8) & 0xFF] ^ TABLES[0][x & 0xFF])
        for i in range(8 * blocks, n):
            crc = TABLES[0][((crc >> 56) ^ data[i]) & 0xFF] ^ (crc << 8)
    return crc
