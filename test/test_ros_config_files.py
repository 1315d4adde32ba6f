"""The parameter files of config/ apply to their nodes in any namespace and under any remap:
every top-level key is ``/**`` or ``/**/<node name>`` (a plain ``<node name>:`` key silently
stops applying under ``-r __ns:=/arm``, and the node runs on its defaults)."""
import glob
import os

import yaml

from conftest import REPO_ROOT, module_domain


def test_every_parameter_file_key_matches_any_namespace():
    files = sorted(glob.glob(os.path.join(REPO_ROOT, 'config', '*.yaml')))
    assert files
    for path in files:
        with open(path) as f:
            doc = yaml.safe_load(f)
        for key in doc:
            assert key == '/**' or key.startswith('/**/'), f'{path}: key {key!r}'
            assert 'ros__parameters' in doc[key], f'{path}: {key} has no ros__parameters'


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
