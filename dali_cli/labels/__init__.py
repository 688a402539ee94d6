"""Pseudo labels: running a detector over target frames at a scale and turning its raw
detections into a box table (NMS, score cut, plausibility rule, size correction, box fit).

May import: ``dali_cli.store``, ``dali_cli.runtime``, ``dali_cli.geometry``,
``dali_cli.detector``, ``dali_cli.ptsn``, ``dali_cli.executors``, ``dali_cli.ppcg``.
"""
