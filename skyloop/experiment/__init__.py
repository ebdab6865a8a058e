"""Experiments: grids of ``skyloop train`` runs on Ray Tune and their reports.

``grid`` reads grid files (pure), ``run`` runs them on Ray Tune, ``report`` turns the
trial directories into ``REPORT.md``, ``summary.json`` and figures.
"""
