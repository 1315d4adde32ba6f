"""The signals between a graph launcher and its node processes (standard library only, so every
layer may use it): :mod:`cdmp_ros.ros.node_main` handles them in each node,
:mod:`cdmp_ros.cli.cmd_bringup` sends them."""
import signal

#: Signals that stop a node (exit code 0 after its ``close()``).
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)
#: Makes a node write the Python stack of every thread to its stderr (``cdmp bringup`` sends it
#: to a node that has not stopped within ``stop_timeout``, before SIGKILL).
DUMP_SIGNAL = signal.SIGUSR1
