"""The ``cdmp`` command-line tool.

Subcommands are discovered: every module ``cdmp_ros/cli/cmd_<name>.py`` defines ``NAME``,
``HELP``, ``add_arguments(parser)`` and ``run(args) -> int``. Modules must import heavy
dependencies (pybullet, matplotlib, rclpy users) inside ``run`` so that ``cdmp --help`` is fast.
"""
import argparse
import importlib
import pkgutil
import sys
from typing import List, Optional

import cdmp_ros.cli as cli_pkg
from cdmp_ros.core.errors import CdmpError


def _subcommand_modules():
    for info in sorted(pkgutil.iter_modules(cli_pkg.__path__), key=lambda i: i.name):
        if info.name.startswith('cmd_'):
            yield importlib.import_module(f'cdmp_ros.cli.{info.name}')


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog='cdmp',
        description='cdmp_ros: constrained movement primitives for ROS 2 (CDMP, constrained '
                    'ProMP). Run "cdmp <command> --help" for the options of a command.')
    sub = parser.add_subparsers(dest='command', metavar='<command>')
    sub.required = True
    for module in _subcommand_modules():
        p = sub.add_parser(module.NAME, help=module.HELP,
                           description=getattr(module, 'DESCRIPTION', module.HELP))
        module.add_arguments(p)
        p.set_defaults(_run=module.run)
    return parser


def main(argv: Optional[List[str]] = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args._run(args) or 0)
    except CdmpError as exc:
        print(f'cdmp {args.command}: error: {exc}', file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == '__main__':
    sys.exit(main())
