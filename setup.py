"""ament_python packaging of cdmp_ros (also installable with plain pip)."""
from glob import glob
import os

from setuptools import find_packages, setup

package_name = 'cdmp_ros'

# Every executable named in the design. Nodes are added here as they become real.
CONSOLE_SCRIPTS = [
    'cdmp = cdmp_ros.cli.main:main',
    'streamer = cdmp_ros.nodes.streamer:main',
    'adapter = cdmp_ros.nodes.adapter:main',
    'sim = cdmp_ros.nodes.sim:main',
    'recorder = cdmp_ros.nodes.recorder:main',
    'player = cdmp_ros.nodes.player:main',
    'learner = cdmp_ros.nodes.learner:main',
]


def _files(pattern):
    return sorted(f for f in glob(pattern, recursive=True) if os.path.isfile(f))


setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test', 'test.*']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/config', _files('config/*.yaml') + _files('config/*.xml')),
        ('share/' + package_name + '/config/graphs', _files('config/graphs/*.yaml')),
        ('share/' + package_name + '/config/joint_limits', _files('config/joint_limits/*.yaml')),
        *[('share/' + package_name + '/' + os.path.dirname(f), [f])
          for f in _files('config/robots/*/*.yaml')],
        ('share/' + package_name + '/urdf', _files('urdf/*.urdf')),
        ('share/' + package_name + '/launch', _files('launch/*.launch.py')),
        ('share/' + package_name + '/msg_schemas', _files('msg_schemas/*.json')),
        ('share/' + package_name + '/msg_schemas/msg', _files('msg_schemas/msg/*.msg')),
        *[('share/' + package_name + '/' + os.path.dirname(f), [f]) for f in _files('bags/**/*')],
    ],
    install_requires=['setuptools', 'numpy', 'scipy', 'jsonschema', 'pyyaml'],
    zip_safe=True,
    maintainer='cdmp_ros maintainers',
    maintainer_email='maintainers@cdmp-ros.org',
    description='Constrained movement primitives (CDMP, constrained ProMP) for ROS 2',
    license='Apache-2.0',
    tests_require=['pytest'],
    entry_points={'console_scripts': CONSOLE_SCRIPTS},
)
