"""cdmp_ros.bag: rosbag2-compatible MCAP bags without ROS (imports core and mcap only).

- :class:`BagWriter` / :class:`BagReader`: bag directories (``metadata.yaml`` + ``.mcap``).
- :func:`recover_bag`: readable bag from a crashed recording, with a report of the loss.
- :func:`read_demonstrations`: ``[(T, Y, joint_names), ...]`` for the learner.
- :func:`bag_info`: verified topics, types, counts and duration.
"""
from cdmp_ros.bag.demos import read_demonstrations
from cdmp_ros.bag.errors import BagCrcError, BagError, BagFormatError, BagTruncatedError
from cdmp_ros.bag.reader import BagMessage, BagReader, bag_info
from cdmp_ros.bag.recovery import RecoveryReport, recover_bag
from cdmp_ros.bag.writer import LOSS_BOUND_S, BagWriter

__all__ = ['BagCrcError', 'BagError', 'BagFormatError', 'BagMessage', 'BagReader',
           'BagTruncatedError', 'BagWriter', 'LOSS_BOUND_S', 'RecoveryReport', 'bag_info',
           'read_demonstrations', 'recover_bag']
