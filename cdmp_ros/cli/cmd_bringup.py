"""``cdmp bringup GRAPH.yaml``: start a graph of cdmp_ros nodes as separate processes and stop
them cleanly (Ctrl-C stops it); ``config/graphs/`` holds the graphs shipped with the package
(``demo.yaml`` is the one ``cdmp demo`` starts).

There is no ``ros2 launch`` on PyPI, so ``cdmp bringup GRAPH.yaml`` does the part of it this
package needs. A graph file::

    # every key but ``nodes`` is optional, and in a node every key but ``executable``
    environment:                 # added to every process (values are strings)
      ROS_DOMAIN_ID: '42'
    stop_timeout: 5.0            # s between SIGINT and SIGKILL at shutdown, in [0.1, 120]
    nodes:
      - name: sim                # process label, unique (default: the executable); the ROS
                                 # node name is unchanged: rename with remappings {__node: ...}
        executable: sim          # learner, adapter, streamer, sim, recorder or player
        params_file: sim.yaml    # relative to the graph file, else to config/ of the package;
                                 # or a list, applied in order (a later file wins), e.g.
                                 # [sim.yaml, robots/planar4/sim.yaml]
        parameters: {publish_rate: 250.0}   # -p name:=value (YAML scalars or lists); they
                                 # win over every params_file
        remappings: {joint_reference: /arm/joint_reference}   # -r from:=to
        namespace: /arm          # -r __ns:=/arm
        arguments: []            # command-line arguments before --ros-args
        required: true           # the graph stops when this process exits (default true)
        delay: 0.0               # s after the previous node was started, in [0, 600]

Each process is ``python -m cdmp_ros.nodes.<executable> --ros-args ...`` with the environment
of the caller plus ``environment``. If ``ROS_AUTOMATIC_DISCOVERY_RANGE`` is unset it is set
to ``LOCALHOST`` (say ``SUBNET`` explicitly to reach other machines). Output lines are prefixed
with the node name. Ctrl-C (SIGINT) or SIGTERM stops every process: the same signal is
forwarded to each node (SIGINT when the graph ends for another reason), SIGKILL after
``stop_timeout`` (a node still running then is first sent SIGUSR1, which makes it write the
stack of each of its threads into the output, and gets :data:`DUMP_WAIT` to do so); the exit
code is 0 when every process stopped cleanly (exit code 0, or ended
by that signal in the first instants of the interpreter, before the node's entry point
installed its handlers, see :mod:`cdmp_ros.ros.node_main`). A node whose rclpy teardown hung
after its ``close()`` returned (ended by its stop backstop, exit code 1) is named as such
(:meth:`Bringup.teardown_hangs`); when no other node failed, the exit code is
:data:`TEARDOWN_HANG_EXIT_CODE` (4) instead of 1. If the launching process dies
without stopping them (SIGKILL, a crash), every node gets SIGTERM from the kernel
(``PR_SET_PDEATHSIG``; Linux): the thread that calls :meth:`Bringup.start` must live as long
as the graph.

``--wait-ready SECONDS`` waits for every learner, adapter, streamer and sim of the graph to log
its first ``ready ... s after start`` line (:mod:`cdmp_ros.ros.readiness_probe`: its topics
matched by peers; streamer and adapter: a primitive received), prints ``bringup: graph ready``
and runs on; when they are not ready in time it names them, stops the graph and exits with
code 3. A launch file waits on the same line with an ``OnProcessIO`` event handler.
"""
import collections
import contextlib
import hashlib
import os
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from typing import Dict, List, Optional, Sequence, Tuple

import yaml

from cdmp_ros.core import cache
from cdmp_ros.core.errors import CdmpError, ValidationError
from cdmp_ros.common.node_signals import DUMP_SIGNAL, teardown_hang
from cdmp_ros.common.prctl import PR_SET_PDEATHSIG, load as prctl_load, prctl
from cdmp_ros.core.readiness import READY_LINE

#: Executables that ``bringup`` can start (modules ``cdmp_ros.nodes.<name>``).
EXECUTABLES = ('learner', 'adapter', 'streamer', 'sim', 'recorder', 'player')
#: Executables that report readiness (:mod:`cdmp_ros.ros.readiness_probe`): their first
#: ``ready ... s after start`` log line (:data:`cdmp_ros.core.readiness.READY_LINE`).
READY_EXECUTABLES = ('learner', 'adapter', 'streamer', 'sim')
#: Exit code of ``cdmp bringup --wait-ready`` when the graph was not ready in time.
NOT_READY_EXIT_CODE = 3
#: Exit code of ``cdmp bringup`` when every node that did not stop cleanly was ended by its stop
#: backstop in rclpy's middleware teardown after its ``close()`` returned
#: (:meth:`Bringup.teardown_hangs`): the nodes did all of their work.
TEARDOWN_HANG_EXIT_CODE = 4
#: Exit codes of a clean stop: 0, or killed by the SIGINT / SIGTERM we sent before the process
#: had installed its handlers (the interpreter still starting).
CLEAN_EXIT_CODES = (0, -signal.SIGINT, -signal.SIGTERM)
#: Output lines kept per process for :meth:`Bringup.teardown_hangs` (a node's stack dump is
#: about 10 lines per thread).
TAIL_LINES = 400
_NODE_KEYS = {'name', 'executable', 'params_file', 'parameters', 'remappings', 'namespace',
              'required', 'delay', 'arguments'}
#: [s] a node that did not stop within stop_timeout gets this long to write its threads' stacks
#: (SIGUSR1) before SIGKILL
DUMP_WAIT = 2.0

_GRAPH_KEYS = {'environment', 'stop_timeout', 'nodes'}

NAME = 'bringup'
HELP = 'start a graph of cdmp_ros nodes (a YAML file) as processes; Ctrl-C stops them cleanly'
DESCRIPTION = (HELP + '. Exit code: 0 when every node stopped cleanly; 1 when one did not; 3 '
               'when --wait-ready ran out; 4 when every node finished its work but the '
               'middleware teardown below rclpy hung in one after its close() returned and its '
               'stop watchdog ended it (named in the output).')
#: The line that names the nodes of :meth:`Bringup.teardown_hangs` (``{nodes}``).
TEARDOWN_HANG_LINE = ("bringup: {nodes}: close() had returned, then rclpy's middleware teardown "
                      'hung and the stop backstop ended the process (its stacks are above); no '
                      'work of the node was lost\n')


def package_config_dir() -> str:
    """``config/`` of the source tree, else ``share/cdmp_ros/config`` of the install."""
    here = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    src = os.path.join(here, 'config')
    if os.path.isdir(src):
        return src
    return os.path.join(sys.prefix, 'share', 'cdmp_ros', 'config')


def _scalar(value) -> str:
    """A parameter value in ``-p name:=value`` syntax (YAML)."""
    if isinstance(value, bool):
        return 'true' if value else 'false'
    if isinstance(value, (list, tuple)):
        return '[' + ', '.join(_scalar(v) for v in value) + ']'
    if isinstance(value, str):
        return "'" + value.replace("'", "''") + "'"
    if isinstance(value, (int, float)):
        return repr(value)
    raise ValidationError(f'parameter value {value!r}: expected a scalar or a list')


def _nest(parameters: Dict[str, object], into: Dict, strict: bool = False) -> Dict:
    """``parameters`` (dotted names) put into the nested dict ``into``, one level per dot;
    returns ``into``. ValidationError for a name below another parameter and, ``strict``, for
    one that is also the prefix of another (``a`` and ``a.b``)."""
    for name, value in parameters.items():
        node = into
        *path, last = name.split('.')
        for part in path:
            node = node.setdefault(part, {})
            if not isinstance(node, dict):
                raise ValidationError(f'parameters: {name!r} is below another parameter')
        if strict and isinstance(node.get(last), dict):
            raise ValidationError(f'parameters: {name!r} is also the prefix of another')
        node[last] = value
    return into


def inline_parameters_file(parameters: Dict[str, object]) -> Optional[str]:
    """A parameter file (``/**: ros__parameters``, one nesting level per dot of a name) with
    ``parameters``, each value written as its ``-p`` form (:func:`_scalar`: the same type
    whichever of the two rcl reads), in the user's cache (:mod:`cdmp_ros.core.cache`, kind
    ``parameters``: ``~/.cache/cdmp_ros/parameters``, mode 0700), named by the hash of its
    text (the same parameters, the same file; written once). Empty lists stay out of it (rcl
    reads ``[]`` in a file as a parameter without a value); None when nothing else is left.

    Raises
    ------
    ValidationError
        A name that is also the prefix of another (``a`` and ``a.b``).
    """
    nested = _nest({k: v for k, v in parameters.items()
                    if not (isinstance(v, (list, tuple)) and not v)}, {}, strict=True)

    def lines(tree: Dict, indent: str) -> List[str]:
        out = []
        for key in sorted(tree):
            if isinstance(tree[key], dict):
                out += [f'{indent}{key}:'] + lines(tree[key], indent + '  ')
            else:
                out.append(f'{indent}{key}: {_scalar(tree[key])}')
        return out
    if not nested:
        return None
    text = '\n'.join(['/**:', '  ros__parameters:'] + lines(nested, '    ')) + '\n'
    return cache.store_or_raise(hashlib.sha1(text.encode()).hexdigest()[:16] + '.yaml', text,
                                cache.locations('parameters'), 'a parameter file')


@dataclass(frozen=True)
class NodeSpec:
    """One process of a graph (see the module docstring)."""

    name: str
    executable: str
    #: absolute paths, in the order ROS applies them (a later file wins)
    params_files: Tuple[str, ...] = ()
    parameters: Dict[str, object] = field(default_factory=dict)
    remappings: Dict[str, str] = field(default_factory=dict)
    namespace: Optional[str] = None
    required: bool = True
    delay: float = 0.0
    arguments: Sequence[str] = ()

    def effective_parameters(self) -> Dict:
        """The node's parameters as ROS applies them: its parameter files' ``ros__parameters``
        (under ``/**``, ``/**/<name>``, ``<name>`` or ``/<name>``, and the executable's name),
        a later file's values over an earlier's, the inline ``parameters`` (dotted names) on
        top; nested dicts, one level per dot."""
        params: Dict = {}
        keys = ('/**', self.executable, '/' + self.executable, '/**/' + self.executable,
                self.name, '/' + self.name, '/**/' + self.name)
        for path in self.params_files:
            with open(path) as f:
                doc = yaml.safe_load(f) or {}
            for key in dict.fromkeys(keys):
                if isinstance(doc.get(key), dict):
                    _merge(params, doc[key].get('ros__parameters') or {})
        return _nest(self.parameters, params)

    def command(self) -> List[str]:
        """The argv of the process: the parameter files in order, the inline parameters as
        ``-p`` and, with two or more files, also as a last parameter file
        (:func:`inline_parameters_file`): rclpy (Jazzy) applies ``-p`` over the first
        ``--params-file`` only, so a later file's value of the same parameter won over it."""
        cmd = [sys.executable, '-m', f'cdmp_ros.nodes.{self.executable}', *self.arguments,
               '--ros-args']
        for path in self.params_files:
            cmd += ['--params-file', path]
        inline = inline_parameters_file(self.parameters) if len(self.params_files) > 1 \
            else None
        if inline is not None:
            cmd += ['--params-file', inline]
        for k, v in self.parameters.items():
            cmd += ['-p', f'{k}:={_scalar(v)}']
        for a, b in self.remappings.items():
            cmd += ['-r', f'{a}:={b}']
        if self.namespace:
            cmd += ['-r', f'__ns:={self.namespace}']
        return cmd


@dataclass(frozen=True)
class Graph:
    """A parsed graph file."""

    nodes: List[NodeSpec]
    environment: Dict[str, str] = field(default_factory=dict)
    stop_timeout: float = 5.0


def _merge(into: Dict, values: Dict) -> None:
    """``values`` (nested parameter dicts) over ``into``, parameter by parameter."""
    for k, v in values.items():
        if isinstance(v, dict) and isinstance(into.get(k), dict):
            _merge(into[k], v)
        else:
            into[k] = dict(v) if isinstance(v, dict) else v


def _known_keys(where: str, d: dict, allowed) -> None:
    unknown = sorted(set(d) - allowed)
    if unknown:
        raise ValidationError(f'{where}: unknown keys {unknown}; allowed {sorted(allowed)}')


def _params_files(where: str, value, base_dir: str) -> Tuple[str, ...]:
    """``params_file``: a file name or a list of them, each relative to ``base_dir``, else to
    :func:`package_config_dir` (absolute names as they are) -> absolute paths."""
    if value is None:
        return ()
    names = value if isinstance(value, list) else [value]
    if not names or not all(isinstance(n, str) and n for n in names):
        raise ValidationError(f'{where}.params_file: expected a file name or a non-empty list '
                              f'of file names, got {value!r}')
    out = []
    for i, name in enumerate(names):
        key = f'{where}.params_file' + (f'[{i}]' if isinstance(value, list) else '')
        candidates = [name] if os.path.isabs(name) else [
            os.path.join(base_dir, name), os.path.join(package_config_dir(), name)]
        found = [c for c in candidates if os.path.isfile(c)]
        if not found:
            raise ValidationError(f'{key}: {name!r} not found (looked in {candidates})')
        out.append(os.path.abspath(found[0]))
    return tuple(out)


def _node(i: int, d, base_dir: str) -> NodeSpec:
    where = f'nodes[{i}]'
    if not isinstance(d, dict):
        raise ValidationError(f'{where}: expected a mapping, got {type(d).__name__}')
    _known_keys(where, d, _NODE_KEYS)
    exe = d.get('executable')
    if exe not in EXECUTABLES:
        raise ValidationError(f'{where}.executable: expected one of {list(EXECUTABLES)}, '
                              f'got {exe!r}')
    name = str(d.get('name', exe))
    params_files = _params_files(where, d.get('params_file'), base_dir)
    for key in ('parameters', 'remappings'):
        if not isinstance(d.get(key, {}), dict):
            raise ValidationError(f'{where}.{key}: expected a mapping, got '
                                  f'{type(d[key]).__name__}')
    params = dict(d.get('parameters') or {})
    for k, v in params.items():
        _scalar(v)  # raises naming the value
    delay = d.get('delay', 0.0)
    if not isinstance(delay, (int, float)) or isinstance(delay, bool) or not \
            0.0 <= delay <= 600.0:
        raise ValidationError(f'{where}.delay: expected seconds in [0, 600], got {delay!r}')
    args = d.get('arguments', [])
    if not isinstance(args, list) or not all(isinstance(a, str) for a in args):
        raise ValidationError(f'{where}.arguments: expected a list of strings, got {args!r}')
    required = d.get('required', True)
    if not isinstance(required, bool):
        raise ValidationError(f'{where}.required: expected true or false, got {required!r}')
    return NodeSpec(name=name, executable=exe, params_files=params_files, parameters=params,
                    remappings={str(a): str(b) for a, b in (d.get('remappings') or {}).items()},
                    namespace=d.get('namespace'), required=required, delay=float(delay),
                    arguments=tuple(args))


def parse_graph(data, base_dir: str = '.') -> Graph:
    """Validate a graph mapping (as loaded from YAML); raises ValidationError naming the key."""
    if not isinstance(data, dict):
        raise ValidationError(f'graph: expected a mapping, got {type(data).__name__}')
    _known_keys('graph', data, _GRAPH_KEYS)
    nodes = data.get('nodes')
    if not isinstance(nodes, list) or not nodes:
        raise ValidationError('graph.nodes: expected a non-empty list of nodes')
    specs = [_node(i, d, base_dir) for i, d in enumerate(nodes)]
    names = [s.name for s in specs]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ValidationError(f'graph.nodes: duplicate names {dup}')
    env = data.get('environment') or {}
    if not isinstance(env, dict):
        raise ValidationError('graph.environment: expected a mapping of strings')
    timeout = data.get('stop_timeout', 5.0)
    if not isinstance(timeout, (int, float)) or not 0.1 <= timeout <= 120.0:
        raise ValidationError(f'graph.stop_timeout: expected seconds in [0.1, 120], '
                              f'got {timeout!r}')
    return Graph(nodes=specs, environment={str(k): str(v) for k, v in env.items()},
                 stop_timeout=float(timeout))


def load_graph(path: str) -> Graph:
    """Read and validate a graph file."""
    try:
        with open(path) as f:
            data = yaml.safe_load(f)
    except OSError as exc:
        raise ValidationError(f'graph file {path!r}: {exc.strerror}') from None
    except yaml.YAMLError as exc:
        raise ValidationError(f'graph file {path!r}: not valid YAML: {exc}') from None
    return parse_graph(data, os.path.dirname(os.path.abspath(path)))


def streamer_configs(graph_file: str, overrides: Optional[dict] = None) -> dict:
    """The configs of the streamer node of ``graph_file`` as the node gets them (its parameter
    files, then its inline parameters: :meth:`NodeSpec.effective_parameters`), one per section
    of :data:`cdmp_ros.core.streaming.streamer.PARAMETER_SECTIONS`, ``overrides``
    (``{'section.name': value}``) applied on top. Parameters of the files that are in no
    section (``joint_limits.*``, the node's own) are not configs and are left out.

    Raises
    ------
    ValidationError
        No streamer node, or an inline parameter or override of no section.
    """
    spec = next((s for s in load_graph(graph_file).nodes if s.executable == 'streamer'), None)
    if spec is None:
        raise ValidationError(f'{graph_file}: expected a node with executable streamer')
    return spec_streamer_configs(spec, overrides, graph_file)


def spec_streamer_configs(spec: NodeSpec, overrides: Optional[dict] = None,
                          where: str = 'streamer') -> dict:
    """:func:`streamer_configs` of one streamer :class:`NodeSpec` (e.g. ``NodeSpec('streamer',
    'streamer', (path of config/streamer.yaml,))``: the shipped configuration)."""
    import dataclasses
    from cdmp_ros.core.streaming.streamer import PARAMETER_SECTIONS
    sections = dict(PARAMETER_SECTIONS)
    for key in {**spec.parameters, **(overrides or {})}:
        section = key.rpartition('.')[0]
        if section not in sections:
            raise ValidationError(f'{where}: streamer parameter {key!r}: expected one of '
                                  f'the sections {[k for k in sections if k]} or none')
    params = spec.effective_parameters()
    for key, v in (overrides or {}).items():
        section, _, name = key.rpartition('.')
        (params.setdefault(section, {}) if section else params)[name] = v
    values = {}
    for section, cls in sections.items():
        given = params if section == '' else params.get(section) or {}
        names = {f.name for f in dataclasses.fields(cls)}
        values[section] = {k: tuple(v) if isinstance(v, list) else v
                           for k, v in given.items() if k in names and not isinstance(v, dict)}
    return {k: cls(**values[k]) for k, cls in sections.items()}


def graph_environment(extra: Dict[str, str]) -> Dict[str, str]:
    """The caller's environment + ``extra``; discovery on localhost unless said otherwise."""
    env = dict(os.environ)
    env.update(extra)
    env.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    env.setdefault('PYTHONUNBUFFERED', '1')
    return env


class Bringup:
    """The running processes of a graph.

    Use as a context manager, or call :meth:`start`, then :meth:`wait` (until a required
    process exits or a signal arrives) and :meth:`stop`.
    """

    def __init__(self, graph: Graph, log=None, extra_env: Optional[Dict[str, str]] = None):
        self.graph = graph
        self.log = log if log is not None else sys.stdout
        self.env = graph_environment({**graph.environment, **(extra_env or {})})
        self.procs: Dict[str, subprocess.Popen] = {}
        self._threads: List[threading.Thread] = []
        self._lock = threading.Lock()
        #: process name -> seconds after start at which the node said it was ready
        self.ready: Dict[str, float] = {}
        self._ready_changed = threading.Event()
        #: process name -> its last output lines (what :meth:`teardown_hangs` reads)
        self._tails: Dict[str, collections.deque] = {}

    def _pump(self, name: str, stream) -> None:
        width = max(len(n.name) for n in self.graph.nodes)
        tail = self._tails.setdefault(name, collections.deque(maxlen=TAIL_LINES))
        for line in iter(stream.readline, ''):
            if name not in self.ready:
                m = READY_LINE.search(line)
                if m is not None:
                    self.ready[name] = float(m.group(1))
                    self._ready_changed.set()
            with self._lock:
                tail.append(line)
                self.log.write(f'[{name:<{width}}] {line}')
                self.log.flush()
        stream.close()

    def not_ready(self) -> List[str]:
        """The started processes of :data:`READY_EXECUTABLES` that have not said they are
        ready yet."""
        return [s.name for s in self.graph.nodes
                if s.executable in READY_EXECUTABLES and s.name in self.procs
                and s.name not in self.ready]

    def wait_ready(self, timeout: float, stop_event: Optional[threading.Event] = None
                   ) -> Optional[str]:
        """Block until every node of :data:`READY_EXECUTABLES` said it is ready; returns
        None then, else why not: ``'timeout'``, ``'stopped'`` (``stop_event``) or the name of
        a required process that exited."""
        end = time.monotonic() + timeout
        required = {s.name for s in self.graph.nodes if s.required}
        while self.not_ready():
            for name in self.exited():
                if name in required:
                    return name
            if stop_event is not None and stop_event.is_set():
                return 'stopped'
            remaining = end - time.monotonic()
            if remaining <= 0.0:
                return 'timeout'
            self._ready_changed.wait(min(0.05, remaining))
            self._ready_changed.clear()
        return None

    def start(self) -> None:
        for spec in self.graph.nodes:
            if spec.delay:
                time.sleep(spec.delay)
            proc = subprocess.Popen(spec.command(), env=self.env, stdout=subprocess.PIPE,
                                    stderr=subprocess.STDOUT, text=True,
                                    start_new_session=True,
                                    preexec_fn=_terminate_with_parent(os.getpid()))
            self.procs[spec.name] = proc
            t = threading.Thread(target=self._pump, args=(spec.name, proc.stdout), daemon=True)
            t.start()
            self._threads.append(t)

    def exited(self) -> Dict[str, int]:
        """Processes that have exited, with their exit codes."""
        return {n: p.returncode for n, p in self.procs.items() if p.poll() is not None}

    def wait(self, stop_event: Optional[threading.Event] = None,
             timeout: Optional[float] = None) -> Optional[str]:
        """Block until a required process exits (its name is returned), ``stop_event`` is set
        or ``timeout`` passes (None is returned)."""
        end = None if timeout is None else time.monotonic() + timeout
        required = {s.name for s in self.graph.nodes if s.required}
        while True:
            for name in self.exited():
                if name in required:
                    return name
            if stop_event is not None and stop_event.is_set():
                return None
            if end is not None and time.monotonic() >= end:
                return None
            time.sleep(0.05)

    def stop(self, sig: int = signal.SIGINT) -> Dict[str, int]:
        """Send ``sig`` (SIGINT or SIGTERM) to every running process, SIGKILL the ones still
        alive after ``stop_timeout``; return every exit code (negative = killed by that
        signal)."""
        for p in self.procs.values():
            if p.poll() is None:
                try:
                    os.killpg(p.pid, sig)
                except ProcessLookupError:
                    pass
        end = time.monotonic() + self.graph.stop_timeout
        for name, p in self.procs.items():
            try:
                p.wait(timeout=max(0.0, end - time.monotonic()))
            except subprocess.TimeoutExpired:
                self._kill_stuck(name, p)
        for t in self._threads:
            t.join(timeout=1.0)
        return {n: p.returncode for n, p in self.procs.items()}

    def teardown_hangs(self) -> List[str]:
        """The exited processes whose exit was the stop backstop ending a hang inside rclpy's
        middleware teardown after their ``close()`` returned
        (:func:`cdmp_ros.common.node_signals.teardown_hang`, read from their output)."""
        with self._lock:
            outputs = {n: ''.join(t) for n, t in self._tails.items()}
        return [n for n, c in self.exited().items() if teardown_hang(c, outputs.get(n, ''))]

    def _kill_stuck(self, name: str, p: subprocess.Popen) -> None:
        """SIGKILL a node that did not stop within ``stop_timeout``, after asking it for the
        stack of every thread (:data:`cdmp_ros.common.node_signals.DUMP_SIGNAL`, written into the
        output, so that the log shows where it was stuck)."""
        with self._lock:
            self.log.write(f'[bringup] {name} did not stop within '
                           f'{self.graph.stop_timeout:g} s: its threads follow, then SIGKILL\n')
            self.log.flush()
        try:
            os.kill(p.pid, DUMP_SIGNAL)
            p.wait(timeout=DUMP_WAIT)   # (the dump is a few kB; it may also finish the stop)
        except ProcessLookupError:
            pass
        except subprocess.TimeoutExpired:
            try:
                os.killpg(p.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        p.wait()

    def __enter__(self):
        self.start()
        return self

    def __exit__(self, *exc):
        self.stop()
        return False


def _terminate_with_parent(parent_pid: int):
    """``preexec_fn`` of a graph's node: SIGTERM to the node when the launching process dies,
    however it dies (SIGKILL, a crash: no ``finally`` runs then, and each node has its own
    session, so nothing else would stop it). Linux only; elsewhere a no-op. If the parent
    already died before the call, the child exits at once. The C library is loaded here, in
    the parent: the child of a multi-threaded parent must not load libraries."""
    prctl_load()

    def preexec():
        if not prctl(PR_SET_PDEATHSIG, signal.SIGTERM):
            return
        if os.getppid() != parent_pid:  # the parent died between fork and prctl
            os._exit(1)
    return preexec


class Terminated(CdmpError):
    """A graph run ended by SIGTERM (after its graph was stopped)."""


@contextlib.contextmanager
def signal_flag(*signums: int):
    """Within the block the given signals are recorded instead of acted on: yields
    ``(event, received)``; a signal appends its number to ``received`` and sets ``event``.
    The caller's loop checks the event and stops its graph in an orderly way. The handler
    itself never raises, so a signal cannot interrupt the stop (by default SIGTERM ended the
    interpreter at once: ``cdmp demo`` left its node processes, each in its own session,
    publishing on their domain). Outside the main thread nothing is installed."""
    event, received = threading.Event(), []

    def on_signal(signum, _frame):
        received.append(signum)
        event.set()

    if threading.current_thread() is not threading.main_thread():
        yield event, received
        return
    previous = {s: signal.signal(s, on_signal) for s in signums}
    try:
        yield event, received
    finally:
        for s, h in previous.items():
            signal.signal(s, h)


def run_graph(path: str, duration: Optional[float] = None, log=None,
              wait_ready: Optional[float] = None) -> int:
    """``cdmp bringup``: start, wait for Ctrl-C / SIGTERM / a required exit / ``duration``,
    stop; 0 when every process ended cleanly. With ``wait_ready`` [s], print
    ``bringup: graph ready ...`` once every node of :data:`READY_EXECUTABLES` said it is
    ready, or stop the graph and return :data:`NOT_READY_EXIT_CODE` when they did not within
    that time. 1 when a node did not stop cleanly, :data:`TEARDOWN_HANG_EXIT_CODE` when every
    such node is one of :meth:`Bringup.teardown_hangs`."""
    graph = load_graph(path)
    out = log if log is not None else sys.stdout
    not_ready = False
    with signal_flag(signal.SIGINT, signal.SIGTERM) as (stop, received):  # received: forwarded
        b = Bringup(graph, log=out)
        out.write(f'bringup: starting {len(graph.nodes)} nodes from {path} '
                  f'(ROS_DOMAIN_ID={b.env.get("ROS_DOMAIN_ID", "0")}, discovery '
                  f'{b.env["ROS_AUTOMATIC_DISCOVERY_RANGE"]}); Ctrl-C stops them\n')
        t0 = time.monotonic()
        b.start()
        ended = None
        if wait_ready is not None:
            why = b.wait_ready(wait_ready, stop)
            if why is None:
                each = ', '.join(f'{n} {t:.2f} s' for n, t in b.ready.items())
                out.write(f'bringup: graph ready {time.monotonic() - t0:.2f} s after the start '
                          f'(each node after its own start: {each})\n')
            elif why == 'timeout':
                not_ready = True
                out.write(f'bringup: not ready within {wait_ready:g} s: {", ".join(b.not_ready())}'
                          f' (their /diagnostics status says what they wait for: waiting_for); '
                          f'stopping the graph\n')
            elif why != 'stopped':
                ended = why
        out.flush()
        if ended is None and not not_ready:
            ended = b.wait(stop, None if duration is None
                           else max(0.0, duration - (time.monotonic() - t0)))
        if ended is not None:
            out.write(f'bringup: required node {ended!r} exited with code '
                      f'{b.procs[ended].returncode}; stopping the graph\n')
        codes = b.stop(received[0] if received else signal.SIGINT)
    bad = {n: c for n, c in codes.items() if c not in CLEAN_EXIT_CODES}
    out.write('bringup: ' + ('all nodes stopped cleanly\n' if not bad else
                             f'nodes that did not stop cleanly: {bad}\n'))
    hung = [n for n in b.teardown_hangs() if n in bad]
    if hung:
        out.write(TEARDOWN_HANG_LINE.format(nodes=', '.join(hung)))
    out.flush()
    if set(bad) - set(hung):
        return 1
    if not_ready:
        return NOT_READY_EXIT_CODE
    return TEARDOWN_HANG_EXIT_CODE if hung else 0


def add_arguments(parser):
    parser.add_argument('graph', help='graph file (YAML: nodes with name, executable, '
                                      'params_file, parameters, remappings, namespace, '
                                      'arguments, required, delay), or '
                                      'the name of a graph in config/graphs (e.g. "demo")')
    parser.add_argument('--duration', type=float, default=None,
                        help='stop the graph after this many seconds (default: run until '
                             'Ctrl-C or until a required node exits)')
    parser.add_argument('--check', action='store_true',
                        help='validate the graph file, print the commands and exit')
    parser.add_argument('--wait-ready', type=float, default=None, metavar='SECONDS',
                        help='wait up to SECONDS for every learner, adapter, streamer and sim '
                             'to say it is ready (its topics matched; streamer and adapter: a '
                             'primitive received), print "bringup: graph ready ...", then run '
                             f'on; not ready in time: stop the graph, exit code '
                             f'{NOT_READY_EXIT_CODE}')


def resolve_graph(name: str) -> str:
    if os.path.isfile(name):
        return name
    shipped = os.path.join(package_config_dir(), 'graphs', name + ('' if name.endswith(
        '.yaml') else '.yaml'))
    return shipped if os.path.isfile(shipped) else name


def run(args):
    path = resolve_graph(args.graph)
    if args.check:
        graph = load_graph(path)
        for spec in graph.nodes:
            print(f'{spec.name}: {" ".join(spec.command())}')
        return 0
    if args.wait_ready is not None and not (args.wait_ready > 0.0):
        raise ValidationError(f'--wait-ready: expected a positive number of seconds, got '
                              f'{args.wait_ready}')
    return run_graph(path, duration=args.duration, wait_ready=args.wait_ready)
