"""Topic names of the external contract that several layers use (standard library only, so
every layer may use it): the nodes of :mod:`cdmp_ros.ros` publish on them, :mod:`cdmp_ros.cli`
records and reads them, the benchmarks and tests subscribe to them."""

#: Every node's ``diagnostic_msgs/DiagnosticArray``, publishers and subscribers alike: absolute,
#: as diagnostic_aggregator and rqt_robot_monitor expect (design.md, Topics), so the nodes of
#: every namespace share it and their status names tell them apart
#: (:class:`cdmp_ros.ros.diagnostics.DiagnosticsReporter`). Remappable like any topic
#: (``-r /diagnostics:=/other``).
DIAGNOSTICS_TOPIC = '/diagnostics'
