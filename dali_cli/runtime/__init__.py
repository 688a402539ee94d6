"""The runtime: where and how code runs.

Owns the error types, console output and progress bars, core counts and worker pools, the
torch device choice.

The leaf modules (errors, console, cores, workers) import nothing from dali_cli; ``device``
may import ``dali_cli.runtime.machine``. Nothing here imports a layer above it
(tests/test_layers.py); the training stages' driver is ``dali_cli.detector.training_stage``.
"""
