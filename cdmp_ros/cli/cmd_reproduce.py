"""``cdmp reproduce <experiment>``: reproduce a paper experiment and report beside the paper.

Experiments are discovered: every module ``cdmp_ros/experiments/exp_<name>.py`` defines
``NAME``, ``HELP``, ``add_arguments(parser)`` and ``run(args) -> int``.
"""
import importlib
import pkgutil

import cdmp_ros.experiments as exp_pkg

NAME = 'reproduce'
HELP = 'reproduce a paper experiment (writes results.json, results.md and figures to --out)'


def _experiments():
    for info in sorted(pkgutil.iter_modules(exp_pkg.__path__), key=lambda i: i.name):
        if info.name.startswith('exp_'):
            yield importlib.import_module(f'cdmp_ros.experiments.{info.name}')


def add_arguments(parser):
    sub = parser.add_subparsers(dest='experiment', metavar='<experiment>')
    sub.required = True
    for module in _experiments():
        p = sub.add_parser(module.NAME, help=module.HELP, description=module.HELP)
        module.add_arguments(p)
        p.set_defaults(_experiment_run=module.run)


def run(args):
    return args._experiment_run(args)
