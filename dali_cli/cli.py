"""The `dali` command line: a click group whose subcommands load lazily from dali_cli.commands.

Each command lives in its own module `dali_cli/commands/<module>.py` as an attribute `command`, so
`dali --help` and `dali sensors` start without importing torch.
"""

from __future__ import annotations

import importlib

import click

from dali_cli import __version__
from dali_cli.runtime.errors import ParameterError, StageError

# command name -> its line in `dali --help`; the module under dali_cli.commands that defines its
# `command` is the name with "_" for "-", but for those in MODULES
COMMANDS: dict[str, str] = {
    "sensors": "List the LiDAR sensor profiles of sensors.toml.",
    "synth": "Synthesize a labelled LiDAR frame set (a domain).",
    "library": "Build a 3D model library (CAD, procedural, point models).",
    "eval": "KITTI-protocol AP of predictions against labels.",
    "compare": "AP of several prediction tables with a paired frame bootstrap.",
    "compare-domains": "Point and car statistics of frame sets side by side (real vs synthetic).",
    "import": "Import real data: kitti, kitti-raw, kitti-odometry, nuscenes, openpcdet, waymo.",
    "merge": "One frame set from several (e.g. a target of several drives).",
    "export": "Export boxes, frames and models: KITTI label_2, OpenPCDet, ONNX.",
    "view": "Draw a frame with boxes as a PNG, or every frame as a Rerun recording.",
    "detect": "Boxes of a trained model on your own scans (.bin, .pcd, .npy, drives).",
    "size-norm": "A labelled frame set with cars resized to a model's SN size.",
    "pretrain": "Step 1: train the detector on the labelled source.",
    "ptsn-sweep": "Step 2: find the PTSN scale for the target.",
    "pseudo-label": "Step 3: pseudo-label the target at the PTSN scale.",
    "register": "Optional before track-pseudo: scan poses of a target without them (registration).",
    "track-pseudo": "Optional after step 3: keep pseudo labels that persist over a scan sequence.",
    "ppcg-rc": "Step 4: ray-constrained pseudo point clouds.",
    "ppcg-cf": "Step 5: constraint-free pseudo point clouds.",
    "retrain": "Step 6: retrain on source + RC + CF frames.",
    "self-train": "Optional: fine-tune on the target with its own pseudo labels.",
    "report": "Tables and plots of a run.",
}
MODULES = {"eval": "evaluate", "import": "importers"}


class LazyGroup(click.Group):
    """A group that imports a subcommand's module only when that subcommand is used."""

    def list_commands(self, ctx: click.Context) -> list[str]:
        return list(COMMANDS)

    def get_command(self, ctx: click.Context, name: str) -> click.Command | None:
        if name not in COMMANDS:
            return None
        module = importlib.import_module(
            f"dali_cli.commands.{MODULES.get(name, name.replace('-', '_'))}"
        )
        from dali_cli.commands.common import stage_command_class

        return stage_command_class(module.command)

    def invoke(self, ctx: click.Context):
        """Run the subcommand; the one place a stage's plain errors become click errors."""
        try:
            return super().invoke(ctx)
        except StageError as error:
            raise as_click_error(
                error, self.get_command(ctx, ctx.invoked_subcommand or "")
            ) from None
        except OSError as error:  # outside a stage's commit: name the file, no traceback
            where = f"{error.filename}: " if error.filename else ""
            raise click.ClickException(
                f"{where}{error.strerror or error}; no output was replaced (any previous output "
                "is intact)"
            ) from None
        except MemoryError:
            raise click.ClickException(
                "out of memory; no output was replaced (any previous output is intact). Use "
                "smaller inputs or options, or a machine with more memory"
            ) from None

    def format_commands(self, ctx: click.Context, formatter: click.HelpFormatter) -> None:
        rows = list(COMMANDS.items())
        with formatter.section("Commands"):
            formatter.write_dl(rows)


def flags_of(command: click.Command | None, fields: tuple[str, ...]) -> list[str]:
    """The command-line flags of stage arguments `fields` (`range_m` -> `--range-m`), searched
    in `command` and its subcommands; a field no option carries is shown as is."""
    params: dict[str, click.Parameter] = {}
    pending = [command] if command is not None else []
    while pending:
        current = pending.pop()
        for param in current.params:
            params.setdefault(param.name, param)
        if isinstance(current, click.Group):
            pending.extend(current.commands.values())
    flags = []
    for field in fields:
        param = params.get(field)
        opts = [o for o in getattr(param, "opts", []) if o.startswith("--")]
        flags.append(opts[0] if opts else field)
    return flags


def as_click_error(error: StageError, command: click.Command | None) -> click.ClickException:
    """A `ParameterError` -> usage error (exit 2) naming the flags; other StageErrors -> exit 1."""
    if isinstance(error, ParameterError):
        return click.UsageError(f"{' / '.join(flags_of(command, error.fields))}: {error.message}")
    return click.ClickException(error.message)


@click.group(cls=LazyGroup)
@click.version_option(__version__, prog_name="dali")
def main() -> None:
    """dali: adapt a LiDAR car detector from a labelled source domain to an unlabelled target.

    The DALI method (Lu & Radha, T-RO 2024): pretrain -> ptsn-sweep -> pseudo-label -> ppcg-rc ->
    ppcg-cf -> retrain, iterated. Every stage reads and writes artifact directories with a
    manifest.json and is skipped when up to date. See README.md.
    """


if __name__ == "__main__":
    main()
