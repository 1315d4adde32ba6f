"""``learner`` executable: fits primitives from demonstrations, publishes ``primitive``.

Run: ``ros2 run cdmp_ros learner --ros-args --params-file config/learner.yaml`` or
``python -m cdmp_ros.nodes.learner --ros-args -p kind:=promp``. Services (std_srvs/Trigger):
``~/refit``, ``~/save``, ``~/improve``. The logic is in :mod:`cdmp_ros.core.learning`,
:mod:`cdmp_ros.core.demonstrations` and :mod:`cdmp_ros.core.dmp.improve`, the ROS glue in
:mod:`cdmp_ros.ros.learner_node`. Spun in the loop of
:func:`cdmp_ros.ros.node_main.run_node` (SIGINT/SIGTERM stop a running improvement first).

OpenBLAS runs single-threaded in this process unless ``OPENBLAS_NUM_THREADS`` is set: the fits
work on small matrices (ProMP EM: 140 x 140), where a second BLAS thread only contends with the
other nodes for the cores and makes the fit many times slower.
"""
import os
import sys

from cdmp_ros.ros.node_main import catch_stop_signals, run_node


def main(args=None) -> int:
    catch_stop_signals()  # first: a signal during the imports below ends the node cleanly
    os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')  # before numpy is imported
    from cdmp_ros.ros.learner_node import LearnerNode
    return run_node(LearnerNode, args)


if __name__ == '__main__':
    sys.exit(main())
