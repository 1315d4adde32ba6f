"""Accuracy (and cost) of the saddle-point tail of Q = |x - c|^2, x ~ N(m, S) (issue 29 item 4).

For every geometry of the grid below, the threshold x at which the default approximation
(:func:`cdmp_ros.core.promp.quadratic_tail.quadratic_form_cdf`: Lugannani-Rice, with Daniels'
second-order term above the mean of Q) puts the tail at a level p is found by bisection; the
exact tail at that x comes from the test oracle ``exact_tail`` (test/test_core_quadratic_tail.py:
nested 1-D integrals of closed-form normal probabilities, relative accuracy ~1e-9 at the
tolerance used here, in both tails), and the variants ``second_order='both'`` (the term on both
sides) and ``'none'`` (the first-order formula: the module before issue 29) are evaluated at the
same x. Printed: markdown tables of the worst relative errors P_approx / P_exact - 1 of the tail
per eigenvalue ratio, with where they occur (positive: tail overestimated, conservative;
negative: underestimated, not conservative).

Grid: k = 2 (one small eigenvalue) and k = 3 (one or two small eigenvalues), the other
eigenvalues 1; ratios 1, 1e-1, ..., 1e-6; the offset m - c along the large axis, the small axis
(t in units of the largest standard deviation), the small axis in units of its own standard
deviation ("small/sd") and the diagonal of both, t = 0, 0.5, 1, 2, 3, 5; tail levels 1e-4, 1e-3,
1e-2, 5e-2; both tails (lower: P(Q <= x), a repeller's violation; upper: P(Q > x), a waypoint's
or the smoothness bound's). Each geometry is turned by a seeded random rotation (the closed-form
eigendecompositions are part of what is measured). A k = 1 table (closed form) follows.

Run: .venv/bin/python benchmarks/bench_quadratic_tail.py                 (~4 min, one core)
     .venv/bin/python benchmarks/bench_quadratic_tail.py --quick         (k = 2, k = 3 sample)
     .venv/bin/python benchmarks/bench_quadratic_tail.py --timing-only   (the cost alone)
"""
import argparse
import math
import os
import sys
import time

import numpy as np

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, REPO)
sys.path.insert(0, os.path.join(REPO, 'test'))

from cdmp_ros.core.promp.quadratic_tail import quadratic_form_cdf  # noqa: E402
from test_core_quadratic_tail import exact_tail, imhof_sf  # noqa: E402

RATIOS = (1.0, 1e-1, 1e-2, 1e-3, 1e-4, 1e-5, 1e-6)
LEVELS = (1e-4, 1e-3, 1e-2, 5e-2)
OFFSETS = (0.0, 0.5, 1.0, 2.0, 3.0, 5.0)
DIRECTIONS = ('large', 'small', 'small/sd', 'diagonal')


def rotation(rng, k):
    Q, R = np.linalg.qr(rng.normal(size=(k, k)))
    return Q * np.sign(np.diag(R))


def make_cases(rng, ks=(2, 3)):
    """(k, shape, ratio, direction, t, lam, d2, m, S): eigenvalues lam (ascending), squared
    offsets d2 in the eigenbasis and the rotated moments (center 0)."""
    cases = []
    for k in ks:
        for shape in (('one',) if k == 2 else ('one', 'two')):
            for ratio in RATIOS:
                lam = np.ones(k)
                lam[0] = ratio
                if shape == 'two':
                    lam[1] = ratio
                for direction in DIRECTIONS:
                    for t in OFFSETS:
                        if t == 0.0 and direction != 'large':
                            continue
                        delta = np.zeros(k)
                        if direction == 'large':
                            delta[-1] = t
                        elif direction == 'small':
                            delta[0] = t
                        elif direction == 'small/sd':
                            delta[0] = t * math.sqrt(ratio)
                        else:
                            delta[0] = delta[-1] = t / math.sqrt(2.0)
                        Q = rotation(rng, k)
                        cases.append(dict(k=k, shape=shape, ratio=ratio, direction=direction,
                                          t=t, lam=lam.copy(), d2=delta * delta, m=Q @ delta,
                                          S=(Q * lam) @ Q.T))
    return cases


VARIANTS = ('upper', 'both', 'none')


def tail(m, S, x, side, second_order='upper'):
    P = quadratic_form_cdf(m, S, np.zeros(m.shape[1]), x, second_order=second_order)[0]
    return P if side == 'lower' else 1.0 - P


def quantile(m, S, E, p, side, iters=90):
    """x with tail(x) = p per row, default variant (bisection in log x; the tail is monotone
    in x)."""
    lo = np.log(E) - 60.0
    hi = np.log(E) + 6.0
    for _ in range(iters):
        mid = 0.5 * (lo + hi)
        above = tail(m, S, np.exp(mid), side) > p
        if side == 'lower':
            hi, lo = np.where(above, mid, hi), np.where(above, lo, mid)
        else:
            lo, hi = np.where(above, mid, lo), np.where(above, hi, mid)
    return np.exp(0.5 * (lo + hi))


def measure(cases, eps):
    rows = []
    for k in sorted({c['k'] for c in cases}):
        ck = [c for c in cases if c['k'] == k]
        m = np.repeat(np.array([c['m'] for c in ck]), len(LEVELS), axis=0)
        S = np.repeat(np.array([c['S'] for c in ck]), len(LEVELS), axis=0)
        E = np.sum(m * m, axis=1) + np.trace(S, axis1=1, axis2=2)
        p = np.tile(LEVELS, len(ck))
        for side in ('lower', 'upper'):
            x = quantile(m, S, E, p, side)
            tails = {v: tail(m, S, x, side, v) for v in VARIANTS}
            for i in range(len(x)):
                c = ck[i // len(LEVELS)]
                ex = exact_tail(c['lam'], c['d2'], x[i], upper=(side == 'upper'), eps=eps)
                rows.append(dict(c, side=side, p=p[i], x=x[i], exact=ex,
                                 **{v: tails[v][i] / ex - 1.0 for v in VARIANTS}))
    return rows


def where(r):
    return f"{r['direction']} t={r['t']:g}, p={r['p']:g}"


def table(rows, key, title):
    print(f'\n### {title}\n')
    print('| k | small eigenvalues | ratio | lower tail: max (where) | lower: min (where) | '
          'upper tail: max (where) | upper: min (where) |')
    print('|---|---|---|---|---|---|---|')
    for k, shape in sorted({(r['k'], r['shape']) for r in rows}):
        for ratio in RATIOS:
            sel = [r for r in rows if (r['k'], r['shape'], r['ratio']) == (k, shape, ratio)]
            if not sel:
                continue
            cells = []
            for side in ('lower', 'upper'):
                ss = [r for r in sel if r['side'] == side]
                hi = max(ss, key=lambda r: r[key])
                lo = min(ss, key=lambda r: r[key])
                cells += [f'{hi[key]:+.1%} ({where(hi)})', f'{lo[key]:+.1%} ({where(lo)})']
            print(f'| {k} | {shape} | {ratio:g} | ' + ' | '.join(cells) + ' |')
    for side in ('lower', 'upper'):
        ss = [r for r in rows if r['side'] == side]
        hi = max(ss, key=lambda r: r[key])
        lo = min(ss, key=lambda r: r[key])
        print(f'\nworst over the grid, {side} tail: {hi[key]:+.2%} (k={hi["k"]}, '
              f'{hi["shape"]}, ratio {hi["ratio"]:g}, {where(hi)}), {lo[key]:+.2%} '
              f'(k={lo["k"]}, {lo["shape"]}, ratio {lo["ratio"]:g}, {where(lo)})')


def k1_table():
    """k = 1: Q / lam is a noncentral chi-square with 1 degree of freedom (closed form)."""
    from scipy import stats
    print('\n### k = 1 (noncentrality b^2 = 0 ... 25; closed form)\n')
    print('| second_order | lower: max | lower: min | upper: max | upper: min |')
    print('|---|---|---|---|---|')
    for variant in VARIANTS:
        out = {'lower': [], 'upper': []}
        for nc in (0.0, 0.25, 1.0, 2.0, 4.0, 9.0, 25.0):
            for p in LEVELS:
                for side in ('lower', 'upper'):
                    if nc == 0.0:
                        x = stats.chi2.ppf(p, 1) if side == 'lower' else stats.chi2.isf(p, 1)
                    else:
                        x = stats.ncx2.ppf(p, 1, nc) if side == 'lower' \
                            else stats.ncx2.isf(p, 1, nc)
                    ex = exact_tail([1.0], [nc], x, upper=(side == 'upper'))
                    t = tail(np.array([[math.sqrt(nc)]]), np.ones((1, 1, 1)), np.array([x]),
                             side, variant)[0]
                    out[side].append(t / ex - 1.0)
        print(f'| {variant} | {max(out["lower"]):+.1%} | {min(out["lower"]):+.1%} | '
              f'{max(out["upper"]):+.1%} | {min(out["upper"]):+.1%} |')


def imhof_check(rows, n, rng):
    """Imhof's integral on a sample of the rows: agreement where it converges."""
    idx = rng.choice(len(rows), min(n, len(rows)), replace=False)
    worst, used = 0.0, 0
    for i in idx:
        r = rows[i]
        sf, err = imhof_sf(r['lam'], r['d2'], r['x'])
        if err > 1e-5 * r['exact']:
            continue
        used += 1
        val = sf if r['side'] == 'upper' else 1.0 - sf
        worst = max(worst, abs(val / r['exact'] - 1.0))
    print(f'\nImhof cross-check: {used} of {len(idx)} sampled rows converged (error estimate '
          f'< 1e-5 of the tail); largest relative difference to the reference {worst:.1e}')


def timing(rng, reps):
    """quadratic_form_cdf on 600 3-D rows (~60 % not skipped, both tails), warm-started as the
    optimiser calls it, for the three variants; median wall time per call."""
    n = 600
    S = np.empty((n, 3, 3))
    for i in range(n):
        Q = rotation(rng, 3)
        S[i] = (Q * (1e-4 * np.exp(rng.uniform(np.log(1e-3), 0.0, 3)))) @ Q.T
    m = rng.normal(size=(n, 3))
    m *= (0.05 + 0.03 * rng.uniform(size=n))[:, None] / np.linalg.norm(m, axis=1)[:, None]
    c = np.zeros(3)
    r2 = np.full(n, 0.05 ** 2)
    states = {v: {} for v in VARIANTS}
    ts = {v: [] for v in VARIANTS}
    for j in range(-reps, reps):         # the first half warms up (CPU clock, caches): untimed
        mj = m + 1e-4 * math.sin(j)
        for v in VARIANTS:               # interleaved, so that load changes hit all alike
            t0 = time.perf_counter()
            P, _, _ = quadratic_form_cdf(mj, S, c, r2, states[v], second_order=v)
            if j >= 0:
                ts[v].append(time.perf_counter() - t0)
    out = {v: np.median(ts[v]) * 1e3 for v in VARIANTS}
    active = np.count_nonzero((P > 0.0) & (P < 1.0))
    print(f'\nCost: 600 rows of 3-D ({active} not skipped), warm start, median of {reps} calls: '
          + ', '.join(f"second_order='{v}' {out[v]:.3f} ms" for v in VARIANTS))


def main():
    ap = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    ap.add_argument('--quick', action='store_true', help='k = 2 and every 4th k = 3 geometry')
    ap.add_argument('--seed', type=int, default=0)
    ap.add_argument('--eps', type=float, default=1e-9, help='relative tolerance of the reference')
    ap.add_argument('--imhof', type=int, default=40, help='rows cross-checked by Imhof')
    ap.add_argument('--timing-reps', type=int, default=200)
    ap.add_argument('--timing-only', action='store_true')
    args = ap.parse_args()
    rng = np.random.default_rng(args.seed)
    if args.timing_only:
        timing(rng, args.timing_reps)
        return
    cases = make_cases(rng)
    if args.quick:
        cases = [c for i, c in enumerate(cases) if c['k'] == 2 or i % 4 == 0]
    t0 = time.time()
    rows = measure(cases, args.eps)
    print(f'{len(rows)} tails ({len(cases)} geometries x {len(LEVELS)} levels x 2 sides), '
          f'reference in {time.time() - t0:.0f} s')
    table(rows, 'upper', "Default (second_order='upper': Daniels' term above the mean of Q)")
    table(rows, 'both', "second_order='both' (Daniels' term on both sides)")
    table(rows, 'none', "second_order='none' (first-order Lugannani-Rice: the module before "
          'issue 29)')
    k1_table()
    if args.imhof:
        imhof_check(rows, args.imhof, rng)
    if args.timing_reps:
        timing(rng, args.timing_reps)


if __name__ == '__main__':
    main()
