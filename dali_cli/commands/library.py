"""`dali library build|show`: build a 3D model library artifact (CAD meshes, procedural cars, point models)."""

from __future__ import annotations

import math

import click

from dali_cli import quantities
from dali_cli.commands.common import (
    SEED,
    artifact_options,
    ran_counts,
    tuning_option,
)


@click.group(name="library")
def command() -> None:
    """3D model libraries for PPCG: car meshes (CAD or procedural) and point models."""


def _parse_range(_ctx, _param, value: str | None) -> tuple[float, float] | None:
    if value is None:
        return None
    try:
        low, high = (float(v) for v in value.split(":"))
    except ValueError:
        raise click.BadParameter(f"expected LOW:HIGH, got {value!r}") from None
    if not (math.isfinite(low) and math.isfinite(high) and 0 <= low < high):
        raise click.BadParameter(f"need finite 0 <= LOW < HIGH, got {value!r}")
    problem = quantities.MODEL_LENGTH.problem(high)
    if problem is not None:
        raise click.BadParameter(f"{value!r}: {problem}")
    return low, high


@command.command(name="build")
@click.option("--cad", "cad_dir", type=click.Path(file_okay=False), default=None,
              help="Directory of OBJ/PLY/STL/GLB/GLTF/OFF car meshes (searched recursively; "
                   "materials and textures are ignored).")  # fmt: skip
@tuning_option("--up", default="z", show_default=True,
              help="Up axis of the CAD files (x, y, z, -x, -y, -z).")  # fmt: skip
@tuning_option("--forward", default="x", show_default=True,
              help="Forward (length) axis of the CAD files.")  # fmt: skip
@click.option("--length-m", "length_range", default=None, callback=_parse_range,
              help="Keep CAD models whose native length lies in LOW:HIGH (file units; the paper "
                   "kept 2:8).")  # fmt: skip
@tuning_option("--skip-bad", is_flag=True,
              help="Skip unreadable, degenerate or mis-oriented CAD files (listed in the "
                   "manifest) instead of failing.")  # fmt: skip
@click.option("--procedural", "procedural_count", type=click.IntRange(0, 100_000), default=0,
              show_default=True,
              help="Number of procedural cars to generate (sedan, hatchback, SUV, van, pickup).")  # fmt: skip
@click.option(
    "--seed", type=SEED, default=0, show_default=True, help="Seed of the procedural cars."
)
@tuning_option("--lod", type=click.IntRange(1000, 200000), default=20000, show_default=True,
              help="Approximate triangles per procedural car (5,000-70,000 is the useful range).")  # fmt: skip
@click.option("--points", "points_dir", type=click.Path(exists=True, file_okay=False),
              default=None,
              help="Labelled FrameSet directory (frames.zarr + boxes.parquet) to take point "
                   "models from.")  # fmt: skip
@tuning_option("--min-points", type=click.IntRange(min=1), default=300, show_default=True,
              help="Point models: instances with at least this many points in their box.")  # fmt: skip
@click.option("--label", default="Car", show_default=True, help="Point models: box label to use.")
@artifact_options("Output library directory.")
def build_command(out, no_progress, **options):
    """Build a model library OUT from any combination of --cad, --procedural and --points.

    Meshes are normalized to the unit box centered at the origin (l along +x, up +z) and keep
    their native size; point models are instances with >= --min-points points, stored in
    box-normalized coordinates with their viewing angle. Writes OUT/library.zarr (meshes and
    points), OUT/meshes.parquet, OUT/point_models.parquet and OUT/manifest.json.

    A CAD model is refused when it is not longer than wide and wider than high once --forward and
    --up are applied (probably other axes): the error names the file and the --forward/--up that
    would fix it. --skip-bad skips such files; --force keeps them with a warning in the manifest.
    """
    from stages.library_build import library_build

    outcome = library_build(out, progress=not no_progress, **options)
    if (counts := ran_counts(outcome)) is not None:
        click.echo(
            f"  {counts['meshes']} meshes ({counts['mesh_triangles']} triangles), "
            f"{counts['point_models']} point models ({counts['model_points']} points)"
            + (f", {counts['cad_skipped']} CAD files skipped" if counts["cad_skipped"] else "")
        )


@command.command(name="show")
@click.argument("library_dir", type=click.Path(exists=True, file_okay=False))
def show_command(library_dir):
    """Summarize a model library: meshes by kind and size, point models by size and points."""
    import numpy as np

    from dali_cli.library import read_library

    library = read_library(library_dir)
    lwh = library.mesh_lwh
    click.echo(
        f"{library_dir}: {len(library.meshes)} meshes, {len(library.point_models)} point models"
    )
    if library.meshes:
        kinds: dict[str, int] = {}
        for model in library.meshes:
            kinds[model.kind or "-"] = kinds.get(model.kind or "-", 0) + 1
        triangles = np.array([m.num_triangles for m in library.meshes])
        click.echo("  kinds: " + ", ".join(f"{k} {n}" for k, n in sorted(kinds.items())))
        click.echo(
            f"  triangles per mesh: mean {triangles.mean():.0f}, min {triangles.min()}, max {triangles.max()}"
        )
        click.echo("  native l, w, h mean: " + ", ".join(f"{v:.2f}" for v in lwh.mean(axis=0)))
    if len(library.point_models):
        pm = library.point_models
        click.echo(
            f"  points per model: mean {pm.num_points.mean():.0f}, min {pm.num_points.min()}"
        )
        click.echo("  box l, w, h mean: " + ", ".join(f"{v:.2f}" for v in pm.lwh.mean(axis=0)))
