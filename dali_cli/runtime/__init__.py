"""The runtime: where and how code runs.

Owns the error types, console output and progress bars, core counts and worker pools, the
torch device choice, and the shared driver of the training stages.

The leaf modules (errors, console, cores, workers) import nothing from dali_cli; ``device``
may import ``dali_cli.runtime.machine``; ``training_stage`` (the driver of pretrain, retrain
and self-train) may import every library layer, but no stage or command.
"""
