"""Stage library_build: a model library artifact (library.zarr, meshes.parquet,
point_models.parquet, manifest.json) from CAD meshes, procedural cars and/or point models of a
labelled frame set (dali_cli.library)."""

from __future__ import annotations

import time
from pathlib import Path

from dali_cli.runtime import console
from dali_cli.runtime.errors import ParameterError
from dali_cli.store.manifest import BuildResult, StageOutcome, run_stage

NOTE = "meshes normalized to the unit box (l along +x, w along +y, up +z), native size kept"


def library_build(
    out: str | Path,
    *,
    cad_dir: str | Path | None = None,
    up: str = "z",
    forward: str = "x",
    length_range: tuple[float, float] | None = None,
    skip_bad: bool = False,
    procedural_count: int = 0,
    seed: int = 0,
    lod: int = 20000,
    points_dir: str | Path | None = None,
    min_points: int = 300,
    label: str = "Car",
    force: bool = False,
    dry_run: bool = False,
    progress: bool = True,
) -> StageOutcome:
    """Build a library into `out` from any of `cad_dir`, `procedural_count` cars, `points_dir`.
    With `force`, CAD models of odd proportions are kept (a warning each, in the manifest);
    `progress`: a progress bar on stderr while point models are taken."""
    from dali_cli.library import LibraryError, axis_rotation

    if cad_dir is None and procedural_count == 0 and points_dir is None:
        raise ParameterError(
            ("cad_dir", "procedural_count", "points_dir"), "give at least one of the three"
        )
    if cad_dir is not None and not Path(cad_dir).is_dir():
        raise ParameterError("cad_dir", f"{cad_dir}: directory not found")
    if cad_dir is not None:
        try:
            axis_rotation(up, forward)
        except LibraryError as error:
            raise ParameterError(("up", "forward"), error.message) from None
    params = {
        "cad": cad_dir is not None,
        "up": up,
        "forward": forward,
        "length_m": length_range,
        "skip_bad": skip_bad,
        "procedural": procedural_count,
        "seed": seed,
        "lod": lod,
        "points": points_dir is not None,
        "min_points": min_points,
        "label": label,
    }

    def build(tmp: Path) -> BuildResult:
        from dali_cli.library import point_models_from_frameset, procedural_library, write_library

        started = time.perf_counter()
        meshes, skipped, odd, notes = load_cad(cad_dir, up, forward, length_range, skip_bad, force)
        timings = {"cad_seconds": round(time.perf_counter() - started, 3)}
        started = time.perf_counter()
        if procedural_count:
            meshes += procedural_library(procedural_count, seed, lod)
        timings["procedural_seconds"] = round(time.perf_counter() - started, 3)
        started = time.perf_counter()
        point_models = (
            point_models_from_frameset(points_dir, min_points, label, progress=progress)
            if points_dir
            else None
        )
        timings["point_models_seconds"] = round(time.perf_counter() - started, 3)
        counts = write_library(tmp, meshes, point_models)
        counts["cad_skipped"] = len(skipped)
        counts["cad_odd_proportions_kept"] = odd
        return BuildResult(counts=counts, timings=timings, notes=[*notes, NOTE])

    return run_stage(
        "library",
        out,
        {"cad": cad_dir, "points": points_dir},
        params,
        build,
        force=force,
        dry_run=dry_run,
        seed=seed if procedural_count else None,
    )


def load_cad(cad_dir, up, forward, length_range, skip_bad, keep_odd):
    """(meshes, skipped messages, odd-proportion count, notes) of the CAD directory (none: empty)."""
    from dali_cli.library import load_cad_directory, proportions_problem

    if cad_dir is None:
        return [], [], 0, []
    cad, skipped = load_cad_directory(
        cad_dir, up, forward, length_range, skip_bad, keep_odd_proportions=keep_odd
    )
    notes = [f"skipped {message}" for message in skipped]
    odd = 0
    for model in cad:  # only with force: otherwise such models were refused or skipped
        problem = proportions_problem(model.native_lwh, up, forward)
        if problem:
            odd += 1
            file = Path(cad_dir) / Path(model.model_id).parent / model.source
            notes.append(f"kept (--force) {file}: {problem}")
            console.warn(notes[-1])
    return cad, skipped, odd, notes
