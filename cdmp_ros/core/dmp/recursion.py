"""The second-order linear recursion of the semi-implicit Euler rollout, over all steps at once.

``y[k] = tr * y[k-1] - det * y[k-2] + gain * v[k]`` is what ``scipy.signal.lfilter([gain, 0, 0],
[1, -tr, det], v, zi=...)`` computes. It is solved here with numpy alone, in blocks of
:data:`BLOCK` steps: inside a block, ``y`` is the block's start state carried by the impulse
response ``g`` of the recursion plus the convolution of ``v`` with ``g`` (one matrix product for
every block at once); only the two last values of each block are carried from block to block
in a Python loop (``len(v) / BLOCK`` iterations of 2 x n operations).

Why not lfilter: importing ``scipy.signal`` costs about 1.1 s of CPU (it imports scipy.stats,
interpolate and ndimage), and every node process that rolls a primitive out (streamer,
learner, adapter) paid it at start. The results agree with lfilter to rounding (tested, lfilter
is the oracle in the tests).
"""
import functools

import numpy as np
from numpy.typing import NDArray

#: Largest number of steps per block: the impulse response over a block stays of the order of
#: BLOCK for the near-double roots at 1 of a DMP's recursion; a block costs BLOCK flops per
#: element, and the carry loop runs ``len(v) / BLOCK`` times.
BLOCK = 256
#: Steps solved at once (64 blocks): bounds the temporary arrays of a long rollout.
CHUNK = 64 * BLOCK


def impulse_response(tr: float, det: float, n: int) -> NDArray:
    """``g[0..n-1]`` with ``g[0] = 1``, ``g[1] = tr``, ``g[j] = tr g[j-1] - det g[j-2]``."""
    g = np.empty(n)
    g[0] = 1.0
    if n > 1:
        g[1] = tr
    for j in range(2, n):
        g[j] = tr * g[j - 1] - det * g[j - 2]
    return g


def second_order_recursion(tr: float, det: float, gain: float, v: NDArray, y_prev1: NDArray,
                           y_prev2: NDArray) -> NDArray:
    """``y`` of shape ``v.shape`` (steps along axis 0) with ``y[k] = tr y[k-1] - det y[k-2] +
    gain v[k]``, started from ``y[-1] = y_prev1`` and ``y[-2] = y_prev2`` (each of shape
    ``v.shape[1:]``).

    With the impulse response ``g`` (:func:`impulse_response`), a block that starts at step
    ``s`` is ``y[s+j] = g[j+1] y[s-1] - det g[j] y[s-2] + gain sum_{i<=j} g[j-i] v[s+i]``.
    Steps are taken :data:`CHUNK` at a time (a chunk's temporary arrays are about four times
    its size). Unlike lfilter, a NaN or inf in ``v`` also reaches the steps of its block
    before it (through the product with the block matrix); the rollout discards any result
    that is not finite."""
    v = np.asarray(v, dtype=float)
    m, rest = v.shape[0], v.shape[1:]
    if m == 0:
        return np.empty_like(v)
    cols = int(np.prod(rest, dtype=int))
    v2 = v.reshape(m, cols)
    s1 = np.broadcast_to(np.asarray(y_prev1, dtype=float), rest).reshape(cols).copy()
    s2 = np.broadcast_to(np.asarray(y_prev2, dtype=float), rest).reshape(cols).copy()
    y = np.empty((m, cols))
    for start in range(0, m, CHUNK):
        stop = min(m, start + CHUNK)
        y[start:stop] = _chunk(float(tr), float(det), float(gain), v2[start:stop], s1, s2)
        s1, s2 = y[stop - 1], (y[stop - 2] if stop - start > 1 else s1)
    return y.reshape(v.shape)


def _chunk(tr: float, det: float, gain: float, v: NDArray, s1: NDArray,
           s2: NDArray) -> NDArray:
    """The recursion over ``v`` (steps, columns) from ``y[-1] = s1``, ``y[-2] = s2``."""
    m, cols = v.shape
    n_block = max(2, min(BLOCK, m))  # the carry reads the two last steps of a block
    nb = -(-m // n_block)
    W = _block_matrix(tr, det, gain, n_block)
    # columns: (block, element); rows: the steps of a block, then the block's start state
    X = np.zeros((n_block + 2, nb, cols))
    by_block = X[:n_block].swapaxes(0, 1)  # (block, step in block, column): a view of X
    full = m // n_block
    by_block[:full] = v[:full * n_block].reshape(full, n_block, cols)
    if full < nb:  # the last block, zero-padded
        by_block[full, :m - full * n_block] = v[full * n_block:]
    X2 = X.reshape(n_block + 2, nb * cols)
    # the two last steps of every block started from rest, then the carry from block to block
    P = (W[-2:, :n_block] @ X2[:n_block]).reshape(2, nb, cols)
    a1, b1 = W[-1, n_block], W[-1, n_block + 1]
    a2, b2 = W[-2, n_block], W[-2, n_block + 1]
    S1, S2 = X[n_block], X[n_block + 1]
    for k in range(nb):
        S1[k] = s1
        S2[k] = s2
        s1, s2 = a1 * s1 + b1 * s2 + P[1, k], a2 * s1 + b2 * s2 + P[0, k]
    Y = (W @ X2).reshape(n_block, nb, cols)
    return Y.transpose(1, 0, 2).reshape(nb * n_block, cols)[:m]


@functools.lru_cache(maxsize=32)
def _block_matrix(tr: float, det: float, gain: float, n_block: int) -> NDArray:
    """``[gain * Toeplitz(g) | weights of y[s-1] | weights of y[s-2]]`` (n_block, n_block + 2):
    one block from its start state; cached (rollouts of one primitive share their step)."""
    g = impulse_response(tr, det, n_block + 1)
    lag = np.subtract.outer(np.arange(n_block), np.arange(n_block))
    W = np.empty((n_block, n_block + 2))
    W[:, :n_block] = np.where(lag >= 0, gain * g[np.maximum(lag, 0)], 0.0)
    W[:, n_block] = g[1:]
    W[:, n_block + 1] = -det * g[:n_block]
    W.setflags(write=False)
    return W
