"""Paper reproductions (``cdmp reproduce <name>``), one module ``exp_<name>.py`` each.

Every experiment writes ``results.json`` in one shape,
``{"experiment": str, "rows": [{"name", "ours", "paper", "unit"}, ...]}`` (``paper`` is null
where the paper gives no figure), and ``results.md`` rendering the same rows side by side;
see :mod:`cdmp_ros.experiments.results`.
"""
