"""`dali retrain`: retrain the detector on source + PPCG frame sets (paper Alg. 1)."""

from __future__ import annotations

import click

from dali_cli.commands.common import (
    choice_option,
    input_dir_option,
    out_dir_option,
    renamed_option,
    target_size_options,
    tuning_option,
)
from dali_cli.commands.detector_options import run_training_command, training_options


class GreedyOption(click.Option):
    """A `multiple` option that also takes every following value up to the next option, so
    `--ppcg DIR1 DIR2` and `--ppcg DIR1 --ppcg DIR2` mean the same (click has no nargs=-1 options)."""

    def add_to_parser(self, parser, ctx):
        super().add_to_parser(parser, ctx)
        for name in self.opts:
            option = parser._long_opt.get(name) or parser._short_opt.get(name)
            if option is None:
                continue
            original = option.process

            def process(value, state, original=original, parser=parser):
                values = [value]
                while state.rargs and not state.rargs[0].startswith("-"):
                    values.append(state.rargs.pop(0))
                for item in values:  # a multiple option collects one value per call
                    original(item, state)

            option.process = process


@click.command(name="retrain")
@input_dir_option("--init",
                  help="Previous model directory (RUN/iterN/model): its config and, by default, "
                       "weights.")  # fmt: skip
@input_dir_option("--source", help="Labelled source FrameSet directory with boxes.parquet.")
@click.option("--ppcg", cls=GreedyOption, multiple=True, required=True,
              type=click.Path(exists=True, file_okay=False),
              help="PPCG frame set directories (each a FrameSet + boxes.parquet): --ppcg RC CF.")  # fmt: skip
@out_dir_option("Checkpoint directory to write.")
@choice_option("--init-from", choices=["previous", "scratch"], default="previous", tuning=True,
               help="Start from the --init weights (paper) or from a fresh network (the authors' "
                    "code).")  # fmt: skip
@tuning_option("--mix", default="1:1", show_default=True,
              help="Batches source:PPCG (PPCG sets pooled), or source:set1:set2 for separate "
                   "weights.")  # fmt: skip
@renamed_option("--size-norm", "--source-size", "source_size", type=click.Choice(["init", "sn"]),
                default="init", show_default=True,
                help="init: the source keeps INIT's size normalization; sn: source boxes are "
                    "shifted to the target's expected mean size (--target-profile / "
                    "--target-size, label-free statistics), points scaled with them, so source "
                    "and PPCG labels agree on car size.")  # fmt: skip
@target_size_options(
    "Sensor profile whose car_mean_lwh_m is the target size for --size-norm sn.",
    "Target mean size 'l,w,h' in m for --size-norm sn (overrides the profile).",
)
@click.option("--target-size-from", type=click.Path(exists=True), default=None,
              help="ptsn-sweep directory (or its scale.json) whose E_est is the target size for "
                   "--size-norm sn (what `make iter2` passes).")  # fmt: skip
@click.option("--label", "labels", multiple=True, default=("Car",), show_default=True,
              help="Box labels to train on.")  # fmt: skip
@training_options
def command(init, source, ppcg, out, labels, **options):
    """Retrain on the labelled source plus PPCG frame sets, alternating source and PPCG batches.

    Reads INIT/model.pt + model.json, SOURCE (frames.zarr + boxes.parquet) and each PPCG directory
    (frames.zarr + boxes.parquet); raw target frames are not used. The source keeps INIT's size
    normalization (SN delta or ROS). An epoch is one pass over the source frames. Writes OUT/model.pt,
    model.json, train_log.parquet and manifest.json (same format as pretrain); an interrupted run
    resumes from OUT.resume/. Runs under torchrun like pretrain (docs/scale-out.md).
    """
    from stages.retrain import run_retrain

    run_training_command(
        "retrain", run_retrain, init, source, list(ppcg), out, labels=tuple(labels), **options,
    )  # fmt: skip
