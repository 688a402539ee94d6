"""Reporting: run reports (Markdown tables and plots), aggregation over seeds, paired
bootstrap comparisons and frame views (PNG).

May import: ``dali_cli.store``, ``dali_cli.runtime``, ``dali_cli.evaluation``,
``dali_cli.geometry``, ``dali_cli.ppcg`` (figures). Nothing imports reporting but the
commands and stages.
"""
