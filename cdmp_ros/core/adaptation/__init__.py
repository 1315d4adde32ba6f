"""Constrained ProMP adaptation (paper 003): constraints, problem, solver, settings, and the
adapter's requests."""
