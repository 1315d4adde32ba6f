"""``cdmp bringup GRAPH.yaml``: start a graph of nodes as separate processes (Ctrl-C stops it).

The graph format is documented in :mod:`cdmp_ros.cli.bringup`; ``config/graphs/`` holds the
graphs shipped with the package (``demo.yaml`` is the one ``cdmp demo`` starts).
"""
import os

NAME = 'bringup'
HELP = 'start a graph of cdmp_ros nodes (a YAML file) as processes; Ctrl-C stops them cleanly'


def add_arguments(parser):
    parser.add_argument('graph', help='graph file (YAML: nodes with executable, params_file, '
                                      'parameters, remappings, namespace, required, delay), or '
                                      'the name of a graph in config/graphs (e.g. "demo")')
    parser.add_argument('--duration', type=float, default=None,
                        help='stop the graph after this many seconds (default: run until '
                             'Ctrl-C or until a required node exits)')
    parser.add_argument('--check', action='store_true',
                        help='validate the graph file, print the commands and exit')


def resolve_graph(name: str) -> str:
    from cdmp_ros.cli.bringup import package_config_dir
    if os.path.isfile(name):
        return name
    shipped = os.path.join(package_config_dir(), 'graphs', name + ('' if name.endswith(
        '.yaml') else '.yaml'))
    return shipped if os.path.isfile(shipped) else name


def run(args):
    from cdmp_ros.cli.bringup import load_graph, run_graph
    path = resolve_graph(args.graph)
    if args.check:
        graph = load_graph(path)
        for spec in graph.nodes:
            print(f'{spec.name}: {" ".join(spec.command())}')
        return 0
    return run_graph(path, duration=args.duration)
