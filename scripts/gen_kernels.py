#!/usr/bin/env python3
"""Write the checked-in generated coupling kernels of the Panda (cdmp_ros/core/generated/).

The streamer's tick runs one generated kernel: the whole obstacle coupling
(:func:`cdmp_ros.core.coupling.kernel.compile_coupling`: the forward kinematics and Jacobians of
:mod:`cdmp_ros.core.kinematics.codegen`, then Eq. 7 and 12). For the configurations the product
runs, this script builds the streamer's coupling, takes the generated source and writes it as a
module, plus the index by which the generators find it (:mod:`cdmp_ros.core.generated`):

- ``panda_coupling``: the streamer's code defaults (``StreamerConfig()``, no parameter file:
  joint-axis segments of links 3 and 5) on the Panda of pybullet_data;
- ``panda_demo_coupling``: the streamer of config/streamer.yaml, which the launch files, the
  demo graph (config/graphs/demo.yaml) and ``cdmp bringup`` use: capsules fitted around
  links 3-7 and the hand, a capsule on link 7.

Any other configuration is written into the kernel cache at run time by the same generator.

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
DEMO_GRAPH = os.path.join(ROOT, 'config', 'graphs', 'demo.yaml')


def demo_coupling(chain):
    """The obstacle coupling of the demo graph's streamer, as the node builds it."""
    from cdmp_ros.cli.cmd_bringup import streamer_configs
    from cdmp_ros.core.streaming.streamer import coupling_of
    from cdmp_ros.ros.robot_model import load_collision_capsules
    c = streamer_configs(DEMO_GRAPH)
    return coupling_of(chain, c, load_collision_capsules('', c[''].coupling_capsule_links,
                                                         chain=chain))


def kernels():
    """(module, function, coupling, title) of every checked-in kernel."""
    import pybullet_data
    from cdmp_ros.core.kinematics import panda_chain
    from cdmp_ros.core.streaming.streamer import StreamerConfig, streamer_coupling
    chain = panda_chain(os.path.join(pybullet_data.getDataPath(), 'franka_panda', 'panda.urdf'))
    return [
        ('panda_coupling', 'coupled', streamer_coupling(chain, StreamerConfig()),
         "Panda: the obstacle coupling of the streamer's code defaults (no parameter file)."),
        ('panda_demo_coupling', 'coupled', demo_coupling(chain),
         'Panda: the obstacle coupling of config/streamer.yaml (launch files, the demo graph).'),
    ]


def render():
    """``{path: text}`` of every generated file."""
    from cdmp_ros.core.coupling.kernel import GENERATOR, IMPORTS
    from cdmp_ros.core.generated import render_index, render_module, source_hash
    files, index = {}, {}
    for module, name, coupling, title in kernels():
        source = coupling._coupled.source
        files[os.path.join(OUT, module + '.py')] = render_module(
            source, title, coupling.kernel_description, GENERATOR, IMPORTS, checked_in=True)
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
