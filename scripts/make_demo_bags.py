#!/usr/bin/env python3
"""Generate the sample demonstration bags in bags/ (deterministic: fixed seeds and times).

    .venv/bin/python scripts/make_demo_bags.py [--out bags]

Writes ``<out>/panda_reach/demo_00 .. demo_04`` (5 noisy Panda reaches, 7 joints, seed 6),
``<out>/dual_panda/demo_00 .. demo_02`` (two-arm crossing reaches, 14 joints, seed 7) and
``<out>/planar4_reach/demo_00 .. demo_02`` (planar 4-link arm reaches, 4 joints, seed 8); see
bags/README.md.  Running it twice gives byte-identical files.
"""
import argparse
import os
import sys

import numpy as np

from cdmp_ros.bag.demos import dual_panda_set, panda_reach_set, planar4_reach_set, write_set

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
#: Set name -> (generator, seed).
SETS = {'panda_reach': (panda_reach_set, 6), 'dual_panda': (dual_panda_set, 7),
        'planar4_reach': (planar4_reach_set, 8)}


def make(out: str) -> list:
    """Write every set of :data:`SETS` under ``out``; return the bag directories written."""
    written = []
    for name, (generate, seed) in SETS.items():
        written += write_set(os.path.join(out, name), generate(np.random.default_rng(seed)))
    return written


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--out', default=os.path.join(ROOT, 'bags'))
    args = parser.parse_args(argv)
    for bag in make(args.out):
        size = sum(os.path.getsize(os.path.join(bag, f)) for f in os.listdir(bag))
        print(f'{os.path.relpath(bag, args.out)}: {size} bytes')
    return 0


if __name__ == '__main__':
    sys.exit(main())
