"""LZF decompression (the codec of PCD ``binary_compressed``), bounded by the expected size.

A compiled loop (numba, cached on disk): every back reference and literal run is checked to
stay inside the input and the output, so a damaged stream is refused instead of read past.
"""

from __future__ import annotations

from functools import cache

import numpy as np


def _lzf_kernel(src: np.ndarray, dst: np.ndarray) -> int:
    """Decode ``src`` into ``dst``; the bytes written, or -1 when the stream is damaged."""
    ip, op = 0, 0
    n, m = src.shape[0], dst.shape[0]
    while ip < n:
        ctrl = int(src[ip])
        ip += 1
        if ctrl < 32:  # a literal run of ctrl + 1 bytes
            length = ctrl + 1
            if ip + length > n or op + length > m:
                return -1
            dst[op : op + length] = src[ip : ip + length]
            ip += length
            op += length
            continue
        length = ctrl >> 5  # a back reference: 3-bit length (7: one more length byte)
        if length == 7:
            if ip >= n:
                return -1
            length += int(src[ip])
            ip += 1
        if ip >= n:
            return -1
        ref = op - ((ctrl & 0x1F) << 8) - int(src[ip]) - 1
        ip += 1
        length += 2
        if ref < 0 or op + length > m:
            return -1
        for k in range(length):  # byte by byte: the reference may overlap the output
            dst[op + k] = dst[ref + k]
        op += length
    return op


@cache
def _compiled():
    import numba

    return numba.njit(cache=True, nogil=True)(_lzf_kernel)


def lzf_decompress(data: bytes, size: int) -> np.ndarray | None:
    """The ``size`` bytes LZF ``data`` decode to (uint8), or None when they do not decode to
    exactly that many."""
    out = np.empty(size, np.uint8)
    written = _compiled()(np.frombuffer(data, np.uint8), out)
    return out if written == size else None
