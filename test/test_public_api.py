"""The public API at the package's top (``from cdmp_ros import CDMP, ProMP, ...``): every name
resolves to the object of its defining module, is documented, and ``import cdmp_ros`` stays
cheap (names are loaded on first use), so a node process pays only for what it uses."""
import importlib
import inspect
import subprocess
import sys

import pytest

import cdmp_ros


def _run(code):
    proc = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return proc.stdout


@pytest.mark.parametrize('name', cdmp_ros.__all__)
def test_every_public_name_resolves_and_is_documented(name):
    value = getattr(cdmp_ros, name)
    if name == '__version__':
        assert isinstance(value, str)
        return
    module = importlib.import_module(cdmp_ros._API[name])
    assert value is getattr(module, name)
    assert getattr(value, '__module__', module.__name__) == module.__name__, \
        f'{name}: import it from {value.__module__}, where it is defined'
    assert inspect.getdoc(value), f'{name}: no docstring'


def test_dir_lists_the_api_and_unknown_names_raise():
    assert set(cdmp_ros.__all__) <= set(dir(cdmp_ros))
    with pytest.raises(AttributeError, match="no attribute 'not_a_name'"):
        cdmp_ros.not_a_name
    from cdmp_ros import core  # submodules still import as usual
    assert core.__name__ == 'cdmp_ros.core'


def test_importing_the_package_loads_nothing_heavy():
    """``import cdmp_ros`` alone loads neither numpy, scipy nor any module of the package; the
    first use of a name loads its module."""
    out = _run('import sys, cdmp_ros\n'
               'heavy = [m for m in sys.modules if m.split(".")[0] in ("numpy", "scipy") '
               'or m.startswith("cdmp_ros.")]\n'
               'assert not heavy, heavy\n'
               'cdmp_ros.CDMP\n'
               'assert "cdmp_ros.core.dmp.dmp" in sys.modules\n'
               'assert "cdmp_ros.core.adaptation.solver" not in sys.modules\n'
               'print("ok")\n')
    assert out.strip() == 'ok'


def test_the_streamer_node_does_not_import_the_adaptation():
    """The streamer's process imports its node module and what that needs; the constrained
    ProMP adaptation is the adapter's."""
    out = _run('import sys, cdmp_ros.ros.streamer_node\n'
               'bad = [m for m in sys.modules if m.startswith("cdmp_ros.core.adaptation")]\n'
               'assert not bad, bad\n'
               'print("ok")\n')
    assert out.strip() == 'ok'
