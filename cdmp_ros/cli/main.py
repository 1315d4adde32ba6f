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


def add_subcommands(sub, package, prefix: str, dest: str) -> None:
    """One sub-parser per discovered module ``<package>/<prefix><name>.py`` (sorted by module
    name), each defining ``NAME``, ``HELP`` (and optionally a longer ``DESCRIPTION``),
    ``add_arguments(parser)`` and ``run(args)``; the
    module's ``run`` is stored as ``args.<dest>``. Used by ``cdmp`` and ``cdmp reproduce``."""
    for info in sorted(pkgutil.iter_modules(package.__path__), key=lambda i: i.name):
        if info.name.startswith(prefix):
            module = importlib.import_module(f'{package.__name__}.{info.name}')
            p = sub.add_parser(module.NAME, help=module.HELP,
                               description=getattr(module, 'DESCRIPTION', module.HELP))
            module.add_arguments(p)
            p.set_defaults(**{dest: module.run})


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog='cdmp',
        description='cdmp_ros: constrained movement primitives for ROS 2 (CDMP, constrained '
                    'ProMP). Run "cdmp <command> --help" for the options of a command.')
    sub = parser.add_subparsers(dest='command', metavar='<command>')
    sub.required = True
    add_subcommands(sub, cli_pkg, 'cmd_', '_run')
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
