"""Evaluation: KITTI-protocol average precision, the KITTI label format and camera
projection, and bootstrap confidence intervals.

May import: ``dali_cli.store``, ``dali_cli.runtime``, ``dali_cli.geometry``,
``dali_cli.importers`` (the KITTI calibration reader). Never the detector or the stages.
"""
