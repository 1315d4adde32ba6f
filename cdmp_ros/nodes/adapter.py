"""``adapter`` executable: the slow path, adapted primitives from obstacles, goals and constraints.

Run: ``ros2 run cdmp_ros adapter --ros-args --params-file config/adapter.yaml`` or
``python -m cdmp_ros.nodes.adapter --ros-args -p adaptation.alpha:=0.99``. The maths is in
:mod:`cdmp_ros.core.adaptation.requests`, the ROS glue in :mod:`cdmp_ros.ros.adapter_node`.

BLAS is limited to one thread (``OPENBLAS_NUM_THREADS=1`` unless set by the caller) before
numpy is imported: the adaptation is a sequence of small matrix products, for which a
multi-threaded BLAS is several times slower and would steal the streamer's core.
"""
import os
import sys

os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')
os.environ.setdefault('OMP_NUM_THREADS', '1')

from cdmp_ros.ros.node_main import catch_stop_signals, run_node  # noqa: E402


def main(args=None) -> int:
    catch_stop_signals()  # first: a signal during the imports below ends the node cleanly
    from cdmp_ros.ros.adapter_node import AdapterNode
    return run_node(AdapterNode, args)


if __name__ == '__main__':
    sys.exit(main())
