"""Generated kernels as modules a reader can open: checked in for the product's default
configurations, written into the kernel cache for any other.

:mod:`cdmp_ros.core.kinematics.codegen` (forward kinematics and Jacobians) and
:mod:`cdmp_ros.core.coupling.kernel` (the whole obstacle coupling, Eq. 7 and 12) generate
straight-line Python source for one chain and set of points. :func:`load_generated` turns that
source into a function whose code lives in a file:

- the checked-in module of exactly this source, if there is one (found by the SHA-256 of the
  source in :data:`cdmp_ros.core.generated.index.INDEX`): on the Panda of pybullet_data, the
  streamer's code defaults (``panda_coupling``) and config/streamer.yaml's, which the launch
  files and the demo graph use (``panda_demo_coupling``),
  written by ``python scripts/gen_kernels.py``; test/test_core_generated.py regenerates them
  and fails on any difference;
- else a module in the kernel cache (:func:`cache_dir`: ``$CDMP_ROS_KERNEL_CACHE``, else
  ``$CDMP_ROS_CACHE/kernels``, ``$XDG_CACHE_HOME/cdmp_ros/kernels`` or
  ``~/.cache/cdmp_ros/kernels``, :mod:`cdmp_ros.core.cache`; :func:`fallback_dir` if that is
  not usable), named after the function and the hash of its source, with a header
  naming the generator and the configuration. Code is imported from these directories, so
  they must belong to the user and be closed to writes of others (else the source is compiled
  in memory).

Either way tracebacks and profiles point into a file whose first lines say what it is.
"""
import hashlib
import importlib
import importlib.util
import re
import textwrap
import threading
from typing import Callable, Dict, List, Optional, Sequence, Tuple

from cdmp_ros.core import cache

__all__ = ['load_generated', 'lookup', 'cache_dir', 'fallback_dir', 'source_hash',
           'render_module', 'render_index', 'wrap_line']

#: Longest line of a rendered module (flake8's limit in this project).
MAX_LINE = 99


def source_hash(source: str) -> str:
    """SHA-256 (hex) of generated ``source``: the key of :data:`index.INDEX`."""
    return hashlib.sha256(source.encode('utf-8')).hexdigest()


def lookup(source: str, name: str) -> Optional[Callable]:
    """The checked-in function ``name`` generated from exactly ``source``, or None (also for
    an index entry whose module is gone: the caller then compiles ``source`` itself)."""
    from cdmp_ros.core.generated.index import INDEX
    entry = INDEX.get(source_hash(source))
    if entry is None or entry[1] != name:
        return None
    try:
        module = importlib.import_module(f'{__name__}.{entry[0]}')
    except ImportError:
        return None
    return getattr(module, name, None)


_SPLIT = re.compile(r' (?=[-+] )| (?=or )|(?<=,) ')


def _openers(text: str) -> List[int]:
    """Per character, the column after the innermost bracket open there (-1: none)."""
    stack, out = [], []
    for i, ch in enumerate(text):
        if ch in '([{':
            stack.append(i + 1)
        elif ch in ')]}':
            stack.pop()
        out.append(stack[-1] if stack else -1)
    return out


def _enclosed(text: str) -> bool:
    """``text`` is one bracketed group, e.g. ``[a, b]``."""
    opened = _openers(text)
    return text[:1] in '([' and all(c >= 0 for c in opened[:-1]) and opened[-1] < 0


def wrap_line(line: str, limit: int = MAX_LINE) -> List[str]:
    """Break one generated line at ``+``/``-``/``or``/``,`` inside brackets, aligned with the
    innermost open bracket, so that every piece fits in ``limit`` columns (a tuple target or
    an assignment's right-hand side is parenthesised first); same semantics, flake8-clean."""
    if len(line) <= limit:
        return [line]
    m = re.match(r'^(\s*)([\w, ]+?) = (.*)$', line)
    if m:
        indent, target, value = m.groups()
        if ',' in target:
            line = f'{indent}({target}) = {value}'
        elif not _enclosed(value):
            line = f'{indent}{target} = ({value})'
    opened = _openers(line)
    cuts = [k.start() for k in _SPLIT.finditer(line) if opened[k.start()] >= 0]
    out, start, col, last = [], 0, 0, None
    for c in cuts + [len(line)]:
        if col + c - start > limit and last is not None and last > start:
            out.append(' ' * col + line[start:last] if out else line[:last])
            col, start = opened[last], last + 1
        last = c
    out.append(' ' * col + line[start:])
    return out


_MATH = ('acos', 'cos', 'sin', 'sqrt')


def math_imports(source: str) -> List[str]:
    """The import line of the :mod:`math` functions that ``source`` calls."""
    used = [f for f in _MATH if re.search(rf'\b{f}\(', source)]
    return [f'from math import {", ".join(used)}'] if used else []


def render_module(source: str, title: str, description: str, generator: str,
                  imports: Sequence[str] = (), checked_in: bool = False) -> str:
    """The text of one kernel module: header (title, generator, configuration, SHA-256 of the
    source), the imports of the math it calls and ``imports``, the generated functions (lines
    wrapped)."""
    body = []
    for line in source.rstrip('\n').split('\n'):
        body += wrap_line(line)
    how = ('Checked in, written by ``python scripts/gen_kernels.py``: do not edit; regenerate '
           'with that\ncommand (test/test_core_generated.py fails on any difference).'
           if checked_in else
           'Written at run time into the kernel cache: do not edit (the file name holds the '
           'hash of the\nsource; another configuration gets another file).')
    doc = [f'"""{title}', '', f'Generated by ``{generator}``.', how, '']
    for line in description.rstrip('\n').split('\n') if description else ():
        doc += textwrap.wrap(line, MAX_LINE - 4, break_long_words=False,
                             break_on_hyphens=False) or ['']
    if description:
        doc.append('')
    doc += [f'Generated-source SHA-256: {source_hash(source)}', '"""']
    lines = math_imports(source)
    if imports:
        lines += ([''] if lines else []) + list(imports)
    return '\n'.join(doc + lines + ['', ''] + body) + '\n'


def render_index(entries: Dict[str, Tuple[str, str]]) -> str:
    """The text of :mod:`index`: ``INDEX = {sha256: (module, function)}``."""
    lines = ['"""Generated by ``python scripts/gen_kernels.py``: do not edit. SHA-256 of each',
             "checked-in kernel's generated source -> (module, function); see the package",
             'docstring."""', '', 'INDEX = {']
    for key in sorted(entries):
        module, name = entries[key]
        lines.append(f"    '{key}':")
        lines.append(f"        ('{module}', '{name}'),")
    return '\n'.join(lines + ['}']) + '\n'


def cache_dir() -> str:
    """Directory of the kernels written at run time (module docstring)."""
    return cache.cache_dir('kernels', 'CDMP_ROS_KERNEL_CACHE')


_LOADED: Dict[str, Callable] = {}
_LOCK = threading.Lock()


def fallback_dir() -> str:
    """The temporary directory of the kernels when :func:`cache_dir` is not writable."""
    return cache.fallback_dir('kernels')


def _cached(source: str, name: str, text: str) -> Callable:
    """The function ``name`` of ``text`` written into the kernel cache (or a private temporary
    directory) and imported from there; compiled in memory only if neither is usable."""
    key = source_hash(source)
    filename = f'{name}_{key[:20]}.py'
    path, errors = cache.store(filename, text, (cache_dir(), fallback_dir()))
    if path is None:
        scope: dict = {}
        exec(compile(text, f'<generated, not written: {"; ".join(errors)}>', 'exec'),  # noqa: S102
             scope)
        return scope[name]
    spec = importlib.util.spec_from_file_location(f'cdmp_ros_kernel_{name}_{key[:20]}', path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return getattr(module, name)


def load_generated(source: str, name: str, title: str, description: str,
                   generator: str, imports: Sequence[str] = ()) -> Callable:
    """The function ``name`` of generated ``source``, from a file (module docstring).

    ``title`` and ``description`` (the configuration) and ``generator`` (the generating
    function) go into the header of a module written into the cache, ``imports`` (lines) into
    its imports besides :mod:`math`. The result carries
    ``.source`` (the generated source) and ``.path`` (its file)."""
    key = source_hash(source)
    with _LOCK:
        fn = _LOADED.get(key)
        if fn is None or fn.__name__ != name:
            fn = lookup(source, name)
            if fn is None:
                fn = _cached(source, name, render_module(source, title, description,
                                                         generator, imports))
            fn.source = source
            fn.path = fn.__code__.co_filename
            if len(_LOADED) > 256:
                _LOADED.clear()
            _LOADED[key] = fn
    return fn
