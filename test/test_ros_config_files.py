"""The parameter files of config/ apply to their nodes in any namespace and under any remap:
every top-level key is ``/**`` or ``/**/<node name>`` (a plain ``<node name>:`` key silently
stops applying under ``-r __ns:=/arm``, and the node runs on its defaults)."""
import glob
import os

import yaml

from conftest import REPO_ROOT, module_domain


def test_every_parameter_file_key_matches_any_namespace():
    files = sorted(glob.glob(os.path.join(REPO_ROOT, 'config', '*.yaml')) +
                   glob.glob(os.path.join(REPO_ROOT, 'config', 'robots', '*', '*.yaml')))
    assert files and any('robots' in f for f in files)
    for path in files:
        with open(path) as f:
            doc = yaml.safe_load(f)
        for key in doc:
            assert key == '/**' or key.startswith('/**/'), f'{path}: key {key!r}'
            assert 'ros__parameters' in doc[key], f'{path}: {key} has no ros__parameters'


def _flat(params, prefix=''):
    out = {}
    for k, v in params.items():
        out.update(_flat(v, f'{prefix}{k}.') if isinstance(v, dict) else {f'{prefix}{k}': v})
    return out


def test_a_robot_file_holds_only_what_differs_from_the_node_file():
    """config/robots/<robot>/<node>.yaml, applied after config/<node>.yaml, sets parameters the
    node's file lists (no misspelt name, which a node would refuse, none it could not take)
    to other values of the same type (nothing that is already the Panda's)."""
    overlays = sorted(glob.glob(os.path.join(REPO_ROOT, 'config', 'robots', '*', '*.yaml')))
    assert overlays
    for path in overlays:
        with open(os.path.join(REPO_ROOT, 'config', os.path.basename(path))) as f:
            base = _flat(yaml.safe_load(f)['/**']['ros__parameters'])
        with open(path) as f:
            robot = _flat(yaml.safe_load(f)['/**']['ros__parameters'])
        assert robot, path
        for name, value in robot.items():
            assert name in base, f'{path}: {name} is not in the node file'
            assert value != base[name], f'{path}: {name} is the same as in the node file'
            kinds = {type(v) for v in (value if isinstance(value, list) else [value])}
            base_kinds = {type(v) for v in (base[name] if isinstance(base[name], list)
                                            else [base[name]])}
            # (an empty list in the node file, e.g. tip_links: [], has no element type: the
            # node's parameter descriptor then checks the overlay's)
            assert kinds == base_kinds or base[name] == [], \
                f'{path}: {name}: {kinds} for {base_kinds}'


def test_a_node_in_a_namespace_gets_its_parameters_from_bag_yaml(tmp_path):
    """rcl applies ``/**/player`` to /arm/player: checked on a copy with a non-default rate."""
    import rclpy
    with open(os.path.join(REPO_ROOT, 'config', 'bag.yaml')) as f:
        doc = yaml.safe_load(f)
    doc['/**/player']['ros__parameters']['rate'] = 3.0
    path = tmp_path / 'bag.yaml'
    path.write_text(yaml.safe_dump(doc))
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=module_domain(12),
               args=['--ros-args', '--params-file', str(path), '-r', '__ns:=/arm'])
    try:
        node = rclpy.create_node('player', context=ctx)
        assert node.get_namespace() == '/arm'
        assert node.declare_parameter('rate', 1.0).value == 3.0
        node.destroy_node()
    finally:
        rclpy.try_shutdown(context=ctx)
