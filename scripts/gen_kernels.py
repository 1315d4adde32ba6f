#!/usr/bin/env python3
"""Write the checked-in generated kernels of the Panda (cdmp_ros/core/generated/).

The streamer's tick on the Panda of pybullet_data with the default parameters
(:func:`cdmp_ros.core.streaming.streamer.streamer_coupling`) runs one generated kernel: the
whole coupling (:func:`cdmp_ros.core.coupling.kernel.compile_coupling`: the forward kinematics
and Jacobians of :mod:`cdmp_ros.core.kinematics.codegen`, then Eq. 7 and 12). This script
builds that coupling, takes the generated source and writes it as a module, plus the index by
which the generators find it (:mod:`cdmp_ros.core.generated`). Kernels of other chains or
points (velocity-dependent fields, the experiments) are compiled at run time.

Usage::

    .venv/bin/python scripts/gen_kernels.py            # rewrite the modules
    .venv/bin/python scripts/gen_kernels.py --check    # exit 1 if any differs (CI)
"""
import argparse
import difflib
import os
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
OUT = os.path.join(ROOT, 'cdmp_ros', 'core', 'generated')

COUPLING_DOC = '''\
The obstacle coupling of the streamer's default configuration (paper 000, Eq. 7 and 12), as
:func:`cdmp_ros.core.coupling.kernel.compile_coupling` generates it for: the Panda of
pybullet_data (franka_panda/panda.urdf, base at the origin), the end-effector term on the tool
centre point (panda_hand + (0, 0, 0.105): the fingertips), the link terms on the segments of
panda_link3 and panda_link5 (``Chain.link_segments``), the limit-aware Eq. (12) with the
``CouplingConfig`` defaults (``limit(q)`` is called only outside the bounds written inline).

``coupled(q, gate, obstacles, eps2, lam2, limit)``: the frame recursion (``q0..q6``, cosines
and sines, constant transforms folded), the world positions of the tool centre point and of
the segment ends passed to ``gate`` (the closest points and fields,
:class:`cdmp_ros.core.coupling.obstacle.ClosestPointGate`), then the Jacobians and the damped
inverses of Eq. (7) and (12). The names follow :mod:`cdmp_ros.core.coupling.kernel`: ``a``
and ``h`` the Gram matrix ``J J^T`` and its damped inverse, ``c`` Eq. (7), ``k``, ``w``, ``s``,
``g``, ``u`` the link blocks, ``acc`` the ``J_o^T u`` sums, ``b`` and ``sw`` the weighted
(limit-aware) branch; ``v<n>`` are intermediate values.'''


def kernels():
    """(module, function, source, title, description, imports) of every checked-in kernel."""
    import pybullet_data
    from cdmp_ros.core.kinematics import panda_chain
    from cdmp_ros.core.streaming.streamer import StreamerConfig, streamer_coupling
    chain = panda_chain(os.path.join(pybullet_data.getDataPath(), 'franka_panda', 'panda.urdf'))
    coupling = streamer_coupling(chain, StreamerConfig())
    trig = 'from math import cos, sin'
    return [
        ('panda_coupling', 'coupled', coupling._coupled.source,
         "Panda: the streamer's default obstacle coupling, one configuration on plain floats.",
         COUPLING_DOC,
         [trig, '', 'from cdmp_ros.core.coupling.terms import _inverse_h3 as inverse_h3']),
    ]


def render():
    """``{path: text}`` of every generated file."""
    from cdmp_ros.core.generated import render_index, render_module, source_hash
    files, index = {}, {}
    for module, name, source, title, doc, imports in kernels():
        files[os.path.join(OUT, module + '.py')] = render_module(source, title, doc, imports)
        index[source_hash(source)] = (module, name)
    files[os.path.join(OUT, 'index.py')] = render_index(index)
    return files


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--check', action='store_true',
                        help='compare with the checked-in files; exit 1 on any difference')
    args = parser.parse_args(argv)
    stale = []
    for path, text in render().items():
        old = open(path).read() if os.path.exists(path) else ''
        if old == text:
            continue
        stale.append(path)
        if args.check:
            sys.stdout.writelines(difflib.unified_diff(
                old.splitlines(True), text.splitlines(True), path, path + ' (regenerated)'))
        else:
            with open(path, 'w') as f:
                f.write(text)
    if args.check and stale:
        print(f'\n{len(stale)} generated file(s) differ: run python scripts/gen_kernels.py')
        return 1
    print(('checked ' if args.check else 'wrote ') + (', '.join(
        os.path.relpath(p, ROOT) for p in stale) if stale and not args.check else 'ok'))
    return 0


if __name__ == '__main__':
    sys.exit(main())
