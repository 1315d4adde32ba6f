"""``cdmp reproduce <experiment>``: reproduce a paper experiment and report beside the paper.

Experiments are discovered: every module ``cdmp_ros/experiments/exp_<name>.py`` defines
``NAME``, ``HELP``, ``add_arguments(parser)`` and ``run(args) -> int``.
"""
import cdmp_ros.experiments as exp_pkg
from cdmp_ros.cli.main import add_subcommands

NAME = 'reproduce'
HELP = 'reproduce a paper experiment (writes results.json, results.md and figures to --out)'


def add_arguments(parser):
    sub = parser.add_subparsers(dest='experiment', metavar='<experiment>')
    sub.required = True
    add_subcommands(sub, exp_pkg, 'exp_', '_experiment_run')


def run(args):
    return args._experiment_run(args)
