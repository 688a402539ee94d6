"""The `dali` command line: a click group whose subcommands load lazily from dali_cli.commands.

Each command lives in its own module `dali_cli/commands/<module>.py` as an attribute `command`, so
`dali --help` and `dali sensors` start without importing torch.
"""

from __future__ import annotations

import importlib

import click

from dali_cli import __version__

# command name -> module under dali_cli.commands (each defines `command`)
COMMANDS: dict[str, tuple[str, str]] = {
    "sensors": ("sensors", "List the LiDAR sensor profiles of sensors.toml."),
    "synth": ("synth", "Synthesize a labeled LiDAR frame set (a domain)."),
    "library": ("library", "Build a 3D model library (CAD, procedural, point models)."),
    "eval": ("evaluate", "KITTI-protocol AP of predictions against labels."),
    "import": ("importers", "Import KITTI, nuScenes or OpenPCDet data."),
    "export": ("export", "Export boxes to other formats (KITTI label_2)."),
    "view": ("view", "Draw a frame with boxes as a PNG."),
    "pretrain": ("pretrain", "Stage 1: train the detector on the labeled source."),
    "ptsn-sweep": ("ptsn_sweep", "Stage 2: find the PTSN scale for the target."),
    "pseudo-label": ("pseudo_label", "Stage 3: pseudo-label the target at the PTSN scale."),
    "ppcg-rc": ("ppcg_rc", "Stage 4: ray-constrained pseudo point clouds."),
    "ppcg-cf": ("ppcg_cf", "Stage 5: constraint-free pseudo point clouds."),
    "retrain": ("retrain", "Stage 6: retrain on source + RC + CF frames."),
    "self-train": ("self_train", "Optional: fine-tune on the target with its own pseudo labels."),
    "report": ("report", "Tables and plots of a run."),
}


class LazyGroup(click.Group):
    """A group that imports a subcommand's module only when that subcommand is used."""

    def list_commands(self, ctx: click.Context) -> list[str]:
        return list(COMMANDS)

    def get_command(self, ctx: click.Context, name: str) -> click.Command | None:
        if name not in COMMANDS:
            return None
        module = importlib.import_module(f"dali_cli.commands.{COMMANDS[name][0]}")
        return module.command

    def format_commands(self, ctx: click.Context, formatter: click.HelpFormatter) -> None:
        rows = [(name, help_text) for name, (_, help_text) in COMMANDS.items()]
        with formatter.section("Commands"):
            formatter.write_dl(rows)


@click.group(cls=LazyGroup)
@click.version_option(__version__, prog_name="dali")
def main() -> None:
    """dali: adapt a LiDAR car detector from a labeled source domain to an unlabeled target.

    The DALI method (Lu & Radha, T-RO 2024): pretrain -> ptsn-sweep -> pseudo-label -> ppcg-rc ->
    ppcg-cf -> retrain, iterated. Every stage reads and writes artifact directories with a
    manifest.json and is skipped when up to date. See README.md.
    """


if __name__ == "__main__":
    main()
