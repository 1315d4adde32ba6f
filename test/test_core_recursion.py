"""The rollout's second-order linear recursion (``cdmp_ros.core.dmp.recursion``) against its
oracle, ``scipy.signal.lfilter``, which computes the same recursion step by step: block and
chunk boundaries, shapes, the coefficients of DMPs at every dt the package uses, and a non-DMP
(oscillating, nearly unstable) recursion."""
import numpy as np
import pytest
from scipy.signal import lfilter

from cdmp_ros.core.dmp.recursion import BLOCK, CHUNK, impulse_response, second_order_recursion


def oracle(tr, det, gain, v, y1, y2):
    zi = np.stack([tr * y1 - det * y2, -det * y1])
    return lfilter([gain, 0.0, 0.0], [1.0, -tr, det], v, axis=0, zi=zi)[0]


def dmp_coefficients(h, alpha=25.0, beta=6.25):
    return 2.0 - h * alpha - h * h * alpha * beta, 1.0 - h * alpha, h * h


@pytest.mark.parametrize('m', [1, 2, 3, BLOCK - 1, BLOCK, BLOCK + 1, 2 * BLOCK + 7, CHUNK + 1,
                               2 * CHUNK + 300])
@pytest.mark.parametrize('h', [0.0005, 0.002, 0.01, 0.05])
def test_equals_lfilter_across_block_boundaries(m, h):
    rng = np.random.default_rng(m)
    tr, det, gain = dmp_coefficients(h)
    v = rng.normal(0.0, 1e3, (m, 3))
    y1, y2 = rng.normal(0.0, 3.0, 3), rng.normal(0.0, 3.0, 3)
    ref = oracle(tr, det, gain, v, y1, y2)
    got = second_order_recursion(tr, det, gain, v, y1, y2)
    assert got.shape == ref.shape
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-11 * np.max(np.abs(ref)))


def test_other_shapes_and_an_oscillating_recursion():
    rng = np.random.default_rng(5)
    tr, det = 2 * 0.999 * np.cos(0.3), 0.999 ** 2  # roots 0.999 exp(+-0.3i)
    for shape in [(700,), (700, 1), (700, 2, 3)]:
        v = rng.normal(size=shape)
        y1, y2 = rng.normal(size=shape[1:]), rng.normal(size=shape[1:])
        ref = oracle(tr, det, 0.7, v.reshape(700, -1), y1.reshape(-1), y2.reshape(-1))
        got = second_order_recursion(tr, det, 0.7, v, y1, y2)
        assert got.shape == shape
        np.testing.assert_allclose(got.reshape(700, -1), ref, rtol=0,
                                   atol=1e-11 * np.max(np.abs(ref)))
    assert second_order_recursion(tr, det, 1.0, np.empty((0, 2)), [0, 0], [0, 0]).shape == (0, 2)


def test_impulse_response_is_the_recursion_from_a_unit_kick():
    tr, det, _ = dmp_coefficients(0.01)
    kick = np.zeros(50)
    kick[0] = 1.0
    np.testing.assert_allclose(impulse_response(tr, det, 50), oracle(tr, det, 1.0, kick, 0, 0),
                               rtol=1e-13, atol=1e-15)
