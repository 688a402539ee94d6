"""Options and helpers shared by the stage commands."""

from __future__ import annotations

import click


def stage_options(function):
    """--force and --dry-run, the two switches every stage command has."""
    function = click.option(
        "--dry-run", is_flag=True, help="Print whether the stage would run, and why; write nothing."
    )(function)
    function = click.option(
        "--force", is_flag=True, help="Rerun even when the output is up to date."
    )(function)
    return function


def sensors_option(function):
    return click.option(
        "--sensors",
        "sensors_path",
        type=click.Path(exists=True, dir_okay=False),
        default=None,
        help="sensors.toml to use instead of the project's.",
    )(function)


def model_target_out_options(model_help: str):
    """--model, --target and --out of the stages that run a model on the target frame set."""

    def decorate(function):
        function = click.option(
            "--out", required=True, type=click.Path(file_okay=False), help="Output directory."
        )(function)
        function = click.option(
            "--target",
            "target_dir",
            required=True,
            type=click.Path(exists=True, file_okay=False),
            help="Target frame set (frames.zarr). Its labels, if any, are never read.",
        )(function)
        return click.option(
            "--model",
            "model_dir",
            required=True,
            type=click.Path(exists=True, file_okay=False),
            help=model_help,
        )(function)

    return decorate


def output_options(function):
    """--out DIR, --sensors and the stage switches of commands that write one artifact."""
    function = stage_options(function)
    function = sensors_option(function)
    return click.option(
        "--out", "out", type=click.Path(file_okay=False), required=True, help="Output directory."
    )(function)


def import_options(default_sensor: str | None):
    """--sensor (the profile recorded with imported frames; required when None) + output_options."""

    def decorate(function):
        function = output_options(function)
        if default_sensor is None:
            return click.option(
                "--sensor", required=True, help="Sensor profile of the data (a sensors.toml name)."
            )(function)
        return click.option(
            "--sensor",
            default=default_sensor,
            show_default=True,
            help="Sensor profile recorded with the frames.",
        )(function)

    return decorate


def device_options(function):
    """--device and --precision, shared by every command that runs the detector (pretrain,
    retrain, self-train, ptsn-sweep, pseudo-label, eval)."""
    function = click.option(
        "--precision",
        type=click.Choice(["fp32", "bf16"]),
        default="fp32",
        show_default=True,
        help="bf16 autocast: for CUDA GPUs with bf16 (Ampere or newer); on a CPU it is faster "
        "only with AMX / AVX512-BF16.",
    )(function)
    return click.option(
        "--device",
        default="auto",
        show_default=True,
        metavar="auto|cpu|cuda|cuda:N",
        help="Where the network runs. auto: CUDA when available, else the CPU. cuda under "
        "torchrun: the GPU of the local rank. A missing GPU is an error (nothing written).",
    )(function)


def workers_option(local_default: str):
    """--workers N: processes (local) or actors (ray) that run the stage's frames."""
    return click.option(
        "--workers",
        type=click.IntRange(min=1),
        default=None,
        help=f"Workers: processes of this machine (--executor local; default {local_default}) or "
        "Ray actors (--executor ray; default one per CPU of the cluster). The output does not "
        "depend on it.",
    )


def executor_options(function):
    """--executor local|ray and --ray-address: the engine that runs a per-frame stage's shards
    (dali_cli.executors; docs/scale-out.md)."""
    function = click.option(
        "--ray-address",
        default=None,
        metavar="ADDR",
        help="With --executor ray: the Ray cluster to use (e.g. HEAD:6379 of `ray start "
        "--head`, or 'auto'). Default: start a local Ray instance for this run.",
    )(function)
    return click.option(
        "--executor",
        type=click.Choice(["local", "ray"]),
        default="local",
        show_default=True,
        help="Engine for the per-frame work: local = this machine (in-process for one worker, "
        "else a process pool); ray = Ray actors, each loading its models once, writing shards "
        "into the output's temporary directory (needs pip install -e '.[ray]'). The output "
        "does not depend on it.",
    )(function)
