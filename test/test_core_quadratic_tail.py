"""cdmp_ros.core.promp.quadratic_tail: the saddle-point CDF of |x - c|^2 for Gaussian x.

Checked against two independent computations: an exact cubature of the Gaussian density over
the ball (closed-form radial integral along each direction, numerical integral over the
directions) and Monte Carlo sampling (4 x 10^6 samples, seeded); gradients against central finite
differences. The Gamma moment match of paper 003 (Eq. 15) is shown to miss the same tails.
"""
import numpy as np
import pytest
from scipy import integrate, optimize, special

from cdmp_ros.core.promp.gaussian import gamma_cdf, quadratic_moments
from cdmp_ros.core.promp.quadratic_tail import quadratic_form_cdf


def _erf_diff(a, b):
    """erf(b) - erf(a) without cancellation in either tail."""
    if a > 0:
        return special.erfc(a) - special.erfc(b)
    if b < 0:
        return special.erfc(-b) - special.erfc(-a)
    return special.erf(b) - special.erf(a)


def ball_probability(m, S, c, r):
    """Exact P(|x - c| <= r), x ~ N(m, S), for k = 2 or 3 (test oracle).

    Along a unit direction u from c, the density is exp(-(A rho^2 + 2 B rho + C) / 2) with
    A = u'Pu, B = u'Pe, C = e'Pe (P = S^-1, e = c - m); its radial integral with the weight
    rho^(k-1) is closed-form in erf; the directions are integrated numerically.
    """
    k = m.size
    P = np.linalg.inv(S)
    e = c - m
    C = e @ P @ e
    norm = (2 * np.pi) ** (-k / 2) / np.sqrt(np.linalg.det(S))

    def radial(u):
        A = u @ P @ u
        B = u @ P @ e
        rho0 = -B / A
        g = np.exp(-0.5 * (C - B * B / A))
        t0, t1 = -rho0, r - rho0
        sA = np.sqrt(A / 2)
        gauss = np.sqrt(np.pi / (2 * A)) * _erf_diff(t0 * sA, t1 * sA)   # int e^{-A t^2/2}

        def ex(t):
            return np.exp(-0.5 * A * t * t)
        t1_int = (ex(t0) - ex(t1)) / A                                    # int t e^{..}
        if k == 2:
            return g * (t1_int + rho0 * gauss)
        t2_int = (t0 * ex(t0) - t1 * ex(t1)) / A + gauss / A              # int t^2 e^{..}
        return g * (t2_int + 2 * rho0 * t1_int + rho0 * rho0 * gauss)

    opts = dict(epsabs=1e-15, epsrel=1e-11)
    if k == 2:
        val, _ = integrate.quad(lambda phi: radial(np.array([np.cos(phi), np.sin(phi)])),
                                0, 2 * np.pi, limit=400, **opts)
    else:
        val, _ = integrate.dblquad(
            lambda phi, th: np.sin(th) * radial(np.array(
                [np.sin(th) * np.cos(phi), np.sin(th) * np.sin(phi), np.cos(th)])),
            0, np.pi, 0, 2 * np.pi, **opts)
    return norm * val


def _problem(rng, k, elongation):
    A = rng.normal(size=(k, k))
    Q, _ = np.linalg.qr(A)
    lam = 0.01 * np.exp(rng.uniform(-np.log(elongation), 0, size=k))
    S = Q @ np.diag(lam) @ Q.T
    m = rng.normal(size=k) * 0.15
    return m, S, np.zeros(k)


CASES = [(k, seed, elong) for k in (2, 3) for seed in range(3) for elong in (1.0, 10.0)]


@pytest.mark.parametrize('k,seed,elongation', CASES)
@pytest.mark.parametrize('target', [1e-4, 1e-3, 1e-2])
@pytest.mark.parametrize('side', ['inside', 'outside'])
def test_tail_matches_exact_cubature_within_10_percent(k, seed, elongation, target, side):
    """Relative error <= 10 % for true probabilities in [1e-4, 1e-2], both tails (a repeller
    violated inside the ball, a waypoint violated outside it)."""
    rng = np.random.default_rng(seed)
    m, S, c = _problem(rng, k, elongation)

    def tail_of(P):
        return P if side == 'inside' else 1.0 - P

    # the radius at which the saddle point says the tail is `target`; then one exact cubature
    r = optimize.brentq(lambda r: tail_of(quadratic_form_cdf(
        m[None], S[None], c, np.array([r * r]))[0][0]) - target, 1e-6, 10.0, xtol=1e-14)
    tail_exact = tail_of(ball_probability(m, S, c, r))
    tail = target
    assert 0.5 * target < tail_exact < 2.0 * target
    assert abs(tail / tail_exact - 1.0) <= 0.10


def test_tail_matches_monte_carlo_and_the_gamma_match_does_not():
    """4 x 10^6 seeded samples per case; the saddle point is within 10 % (MC noise <= 1.6 %) while
    the Gamma moment match misses at least one case by far more."""
    rng = np.random.default_rng(7)
    gamma_errors = []
    for k in (2, 3):
        m, S, c = _problem(rng, k, 10.0)
        L = np.linalg.cholesky(S)
        X = m + rng.standard_normal((4_000_000, k)) @ L.T
        q = np.sum((X - c) ** 2, axis=1)
        del X
        for p in (1e-3, 1e-2):
            x = np.quantile(q, p)          # MC lower tail at level p
            p_mc = np.mean(q <= x)
            P, _, _ = quadratic_form_cdf(m[None], S[None], c, np.array([x]))
            assert abs(P[0] / p_mc - 1.0) <= 0.10
            E, V, *_ = quadratic_moments(m[None], S[None], c[None])
            G, _, _ = gamma_cdf(E, V, x)
            gamma_errors.append(abs(G[0] / p_mc - 1.0))
    assert max(gamma_errors) > 0.3


@pytest.mark.parametrize('k', [1, 2, 3, 7])
def test_gradients_match_finite_differences(k):
    rng = np.random.default_rng(k)
    n = 6
    A = rng.normal(size=(n, k, k))
    S = 0.01 * np.matmul(A, np.swapaxes(A, 1, 2)) + 1e-3 * np.eye(k)
    m = rng.normal(size=(n, k)) * 0.2
    c = rng.normal(size=k) * 0.05
    E, V, *_ = quadratic_moments(m, S, np.broadcast_to(c, m.shape))
    # thresholds spread over both tails and the centre
    x = E * np.array([0.05, 0.3, 0.8, 1.3, 2.5, 4.0])
    P, dP_dm, dP_dS = quadratic_form_cdf(m, S, c, x)
    assert np.all((P > 0) & (P < 1))
    h = 1e-6
    for i in range(k):
        dm = np.zeros((n, k))
        dm[:, i] = h
        num = (quadratic_form_cdf(m + dm, S, c, x)[0] - quadratic_form_cdf(m - dm, S, c, x)[0])
        np.testing.assert_allclose(dP_dm[:, i], num / (2 * h), rtol=2e-4, atol=1e-9)
    for i in range(k):
        for j in range(i, k):
            dS = np.zeros((n, k, k))
            dS[:, i, j] = dS[:, j, i] = h * 1e-2
            num = (quadratic_form_cdf(m, S + dS, c, x)[0]
                   - quadratic_form_cdf(m, S - dS, c, x)[0]) / (2 * h * 1e-2)
            ana = dP_dS[:, i, j] + (dP_dS[:, j, i] if i != j else 0.0)
            np.testing.assert_allclose(ana, num, rtol=2e-4, atol=1e-8)


def test_repeated_eigenvalues_and_a_deterministic_point_are_handled():
    """Isotropic covariance (all eigenvalues equal) and a covariance of ~0 (a conditioned
    start point): finite values and gradients, probabilities 0/1 where the point is certain."""
    m = np.array([[0.3, 0.0], [0.3, 0.0], [0.05, 0.0]])
    S = np.stack([0.01 * np.eye(2), 1e-20 * np.eye(2), 1e-20 * np.eye(2)])
    P, dm, dS = quadratic_form_cdf(m, S, np.zeros(2), np.full(3, 0.01))
    assert np.all(np.isfinite(P)) and np.all(np.isfinite(dm)) and np.all(np.isfinite(dS))
    # isotropic: |x|^2 / 0.01 is noncentral chi-square(2, 9)
    from scipy import stats
    np.testing.assert_allclose(P[0], stats.ncx2.cdf(1.0, 2, 9.0), rtol=0.05)
    assert P[1] == pytest.approx(0.0, abs=1e-12)     # certainly outside the 0.1 ball
    assert P[2] == pytest.approx(1.0, abs=1e-12)     # certainly inside
