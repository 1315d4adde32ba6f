"""Helpers that need only the standard library, usable by every layer (core, sim, bag, ros,
nodes, cli) and cheap to import in every node process: the signals between a graph launcher
and its nodes (:mod:`.node_signals`), the ``prctl(2)`` call (:mod:`.prctl`), real-time
scheduling of periodic threads (:mod:`.realtime`), token-bucket rate limits
(:mod:`.rate_limit`) and the latest-request-wins worker thread (:mod:`.latest_worker`).

Nothing here imports numpy, scipy, ROS or any other part of cdmp_ros
(``test/test_architecture.py`` checks it).
"""
