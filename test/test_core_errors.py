"""Every refusal in cdmp_ros is a CdmpError: no ``raise`` of a builtin exception class in the
package source, except the few allow-listed below (each with its reason)."""
import ast
import builtins
import pathlib

import pytest

from cdmp_ros.core.dmp.dmp import CDMP, DmpConfig
from cdmp_ros.core.errors import CdmpError, ValidationError

PACKAGE = pathlib.Path(__file__).resolve().parents[1] / 'cdmp_ros'

#: Builtin exception classes that may be raised anywhere, with the reason.
ALLOWED_EVERYWHERE = {
    'NotImplementedError': 'abstract methods of base classes (a programming error, not an '
                           'input refusal)',
}

#: (path relative to cdmp_ros/, exception class) -> reason.
ALLOWED = {
    ('experiments/exp_promp_tables.py', 'SystemExit'):
        'command-line argument errors of an experiment script end the process with a message',
    ('ros/recorder_take.py', 'RuntimeError'):
        'internal invariant (a thread-taken subscription is never executed by an executor)',
    ('common/realtime.py', 'ValueError'):
        'common is standard library only (no CdmpError); a programming-error guard: the nodes '
        'refuse bad priorities and spins with ValidationError (config ranges) first',
    ('__init__.py', 'AttributeError'):
        'the module __getattr__ protocol of the lazy public API (an unknown name)',
}


def _builtin_raises():
    """(relative path, line, class name) of every ``raise Builtin(...)`` in the package."""
    out = []
    for path in sorted(PACKAGE.rglob('*.py')):
        tree = ast.parse(path.read_text(), filename=str(path))
        for node in ast.walk(tree):
            if not isinstance(node, ast.Raise) or node.exc is None:
                continue
            exc = node.exc.func if isinstance(node.exc, ast.Call) else node.exc
            if not isinstance(exc, ast.Name):
                continue
            cls = getattr(builtins, exc.id, None)
            if isinstance(cls, type) and issubclass(cls, BaseException):
                out.append((path.relative_to(PACKAGE).as_posix(), node.lineno, exc.id))
    return out


def test_no_builtin_exception_is_raised_outside_the_allow_list():
    found = _builtin_raises()
    assert found, 'the scan found no raise at all: it is broken'
    bad = [f'cdmp_ros/{p}:{line}: raise {name}' for p, line, name in found
           if name not in ALLOWED_EVERYWHERE and (p, name) not in ALLOWED]
    assert not bad, ('refusals must raise a cdmp_ros.core.errors.CdmpError subclass '
                     '(ValidationError for a bad input):\n' + '\n'.join(bad))


def test_the_allow_list_has_no_stale_entry():
    found = {(p, name) for p, _, name in _builtin_raises()}
    stale = [k for k in ALLOWED if k not in found]
    assert not stale, f'allow-listed raises that no longer exist: {stale}'


def test_the_scan_catches_a_builtin_raise(tmp_path, monkeypatch):
    (tmp_path / 'mod.py').write_text('def f(x):\n    raise ValueError(x)\n')
    monkeypatch.setitem(globals(), 'PACKAGE', tmp_path)
    assert _builtin_raises() == [('mod.py', 2, 'ValueError')]


def test_the_stepper_refuses_an_unstable_step_with_a_validation_error():
    cdmp = CDMP([-1.0], [1.0], DmpConfig(n_weights_per_dim=5))
    cdmp.set_parameters([[0.0] * 5], [0.0], [0.5], 1.0)
    with pytest.raises(ValidationError, match=r'dt: dt / tau') as info:
        cdmp.stepper(dt=0.5)
    assert isinstance(info.value, (CdmpError, ValueError))
    with pytest.raises(ValidationError, match='velocity_limits'):
        cdmp.stepper(dt=0.001, velocity_limits=[-1.0])
