"""Diagonal 3x3 blocks of the inverse of a block-banded matrix, from its banded Cholesky factor (the GCV trace of
the trajectory fits, reconstruct/trajectory.py).

The fits' systems couple the three coordinates of instant i with instants i-2..i+2: 3x3 blocks, block bandwidth 2.
Takahashi's recursion on those blocks gives the blocks of Z = M^-1 within that band from the last instant backwards,
O(n) small matrix products. Per instant j, with U_k = L_kj L_jj^-1 for k = j+1, j+2:

    Z_ij = -sum_k Z_ik U_k   (i = j+1, j+2),        Z_jj = (L_jj L_jj^T)^-1 - sum_k Z_kj^T U_k.

Everything that does not depend on Z (the U_k and (L_jj L_jj^T)^-1 of every instant) is computed for all instants at
once, so that the loop over instants holds a handful of batched 3x3 products.
"""

from __future__ import annotations

import numpy as np

BLOCK = 3  # unknowns 3i + k
BLOCK_BANDS = 2  # instants coupled on each side
BANDS = BLOCK * BLOCK_BANDS + BLOCK  # lower band rows of the banded factor: |row - column| <= 8
CHUNK = 128  # instants per chunk of `trace_of_inverse_times`: its work arrays stay small


def trace_of_inverse_times(factors: np.ndarray, blocks: np.ndarray) -> np.ndarray:
    """(B,) tr(M^-1 D) for B systems given by the lower banded Cholesky factors of M, `factors (B, BANDS, 3n)`
    (scipy.linalg.cholesky_banded(lower=True) layout: factors[b, d, c] = L[c + d, c]), and block-diagonal D given by
    its 3x3 blocks `blocks (B, n, 3, 3)`. M must be block-banded as above: the factor's entries outside the blocks'
    band are then zero and not read. Instants are taken in chunks of CHUNK, so that the work arrays stay small."""
    B, bands, N = factors.shape
    if bands != BANDS or N % BLOCK or blocks.shape != (B, N // BLOCK, BLOCK, BLOCK):
        raise ValueError(f"factors {factors.shape} and blocks {blocks.shape}: expected (B, {BANDS}, 3n), (B, n, 3, 3)")
    n = N // BLOCK
    trace = np.zeros(B)
    after = np.zeros((2 * BLOCK, 2 * BLOCK, B))  # the window of the instant after the current one
    for stop in range(n, 0, -CHUNK):
        begin = max(0, stop - CHUNK)
        U, first = _chunk_terms(factors, begin, stop)
        D = np.ascontiguousarray(blocks[:, begin:stop].transpose(1, 3, 2, 0))  # (c, 3, 3, B), D_j^T
        after = _recursion(U, first, D, after, trace)
    return trace


def _chunk_terms(factors: np.ndarray, begin: int, stop: int) -> tuple[np.ndarray, np.ndarray]:
    """U (c, 6, 3, B): U_j+1 over U_j+2, and (L_jj L_jj^T)^-1 (c, 3, 3, B), for instants begin..stop-1."""
    B, _, N = factors.shape
    # V[j, c, d, b] = L[3j + c + d, 3j + c]: the factor column-major with the systems on the last axis, so that every
    # operation runs over contiguous data
    V = np.ascontiguousarray(factors[:, :, BLOCK * begin : BLOCK * stop].transpose(2, 1, 0))
    for d in range(1, BANDS):  # LAPACK leaves the band's corner past the matrix's end undefined
        V[max(0, N - d - BLOCK * begin) :, d] = 0.0
    V = V.reshape(stop - begin, BLOCK, BANDS, B)
    # L_jj^-1 in closed form (lower triangular)
    i00, i11, i22 = 1.0 / V[:, 0, 0], 1.0 / V[:, 1, 0], 1.0 / V[:, 2, 0]
    i10 = -V[:, 0, 1] * i00 * i11
    i21 = -V[:, 1, 1] * i11 * i22
    i20 = (V[:, 0, 1] * V[:, 1, 1] - V[:, 1, 0] * V[:, 0, 2]) * i00 * i11 * i22
    # rows 3..8 of the block column times L_jj^-1; its row r, column m is V[:, m, r - m]
    U = np.empty((stop - begin, 2 * BLOCK, BLOCK, B))
    U[:, :, 0] = V[:, 0, 3:9] * i00[:, None] + V[:, 1, 2:8] * i10[:, None] + V[:, 2, 1:7] * i20[:, None]
    U[:, :, 1] = V[:, 1, 2:8] * i11[:, None] + V[:, 2, 1:7] * i21[:, None]
    U[:, :, 2] = V[:, 2, 1:7] * i22[:, None]
    # L_jj^-T L_jj^-1
    first = np.empty((stop - begin, BLOCK, BLOCK, B))
    first[:, 0, 0] = i00 * i00 + i10 * i10 + i20 * i20
    first[:, 1, 1] = i11 * i11 + i21 * i21
    first[:, 2, 2] = i22 * i22
    first[:, 1, 0] = first[:, 0, 1] = i11 * i10 + i21 * i20
    first[:, 2, 1] = first[:, 1, 2] = i22 * i21
    first[:, 2, 0] = first[:, 0, 2] = i22 * i20
    return U, first


def _recursion(U: np.ndarray, first: np.ndarray, D: np.ndarray, after: np.ndarray, trace: np.ndarray) -> np.ndarray:
    """Takahashi's recursion over one chunk's instants, last first: adds tr(Z_jj D_j) to `trace (B,)` and returns
    the window [[Z_jj, Z_j,j+1], [Z_j+1,j, Z_j+1,j+1]] (6, 6, B) of the chunk's first instant."""
    window = np.empty_like(after)
    for j in range(len(U) - 1, -1, -1):
        below = -np.einsum("ikb,kjb->ijb", after, U[j])  # (6, 3, B): Z_j+1,j over Z_j+2,j
        block = first[j] - np.einsum("kib,kjb->ijb", U[j], below)
        block = 0.5 * (block + block.transpose(1, 0, 2))
        trace += np.einsum("ikb,ikb->b", block, D[j])
        window[:BLOCK, :BLOCK] = block
        window[BLOCK:, :BLOCK] = below[:BLOCK]
        window[:BLOCK, BLOCK:] = below[:BLOCK].transpose(1, 0, 2)
        window[BLOCK:, BLOCK:] = after[:BLOCK, :BLOCK]
        after, window = window, after
    return after
