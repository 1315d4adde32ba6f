#!/usr/bin/env python3
"""Generate the sample demonstration bags in bags/ (deterministic: fixed seeds and times).

    .venv/bin/python scripts/make_demo_bags.py [--out bags]

Writes ``<out>/panda_reach/demo_00 .. demo_04`` (5 noisy Panda reaches, 7 joints, seed 6) and
``<out>/dual_panda/demo_00 .. demo_02`` (two-arm crossing reaches, 14 joints, seed 7); see
bags/README.md.  Running it twice gives byte-identical files.
"""
import argparse
import os
import shutil
import sys

import numpy as np

from cdmp_ros.bag.demos import EPOCH_NS, dual_panda_set, panda_reach_set, write_demonstration

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SEEDS = {'panda_reach': 6, 'dual_panda': 7}


def make(out: str) -> list:
    """Write both sets under ``out``; return the bag directories written."""
    written = []
    sets = {'panda_reach': panda_reach_set(np.random.default_rng(SEEDS['panda_reach'])),
            'dual_panda': dual_panda_set(np.random.default_rng(SEEDS['dual_panda']))}
    for name, demos in sets.items():
        root = os.path.join(out, name)
        if os.path.isdir(root):
            shutil.rmtree(root)
        for i, (T, YYd, names) in enumerate(demos):
            n = len(names)
            bag = os.path.join(root, f'demo_{i:02d}')
            write_demonstration(bag, T, YYd[:, :n], YYd[:, n:], names,
                                start_ns=EPOCH_NS + i * 10 ** 10)
            written.append(bag)
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
