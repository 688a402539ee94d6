"""Benchmark: how far each stage's outputs move when only the CPU's floating point changes.

Runs a chain under each CPU kernel path torch offers on this machine (torch's ATEN_CPU_CAPABILITY
with MKL's and oneDNN's matching settings, below) and each thread count, then reports, stage by
stage, the spread of what it produced: PTSN's ŝ, the pseudo boxes kept, the boxes RC and CF
replaced, the trained weights' distance from the reference path's, and AP. A stage whose spread
is much larger than its input's amplifies rounding.

    .venv/bin/python bench/numerical_stability.py [--chain tiny] [--paths native avx2 avx512 default]
        [--threads 1] [--isolate] [--out bench/results/numerical_stability_tiny.json]
    .venv/bin/python bench/numerical_stability.py --chain demo --threads 2
    .venv/bin/python bench/numerical_stability.py --chain real --data D [--labels L]
        [--model models/kitti-hdl64e]    (the inference stages only: ptsn-sweep, pseudo-label, eval)

Chains: `tiny` and `demo` are `make tiny` / `make demo` (each path its own run directory under
--runs); `real` runs a shipped model's inference stages on an imported real frame set.
`--isolate` (tiny, demo) then reruns each model stage of the first path's run alone under every
other path, on the first path's inputs: what that stage alone makes of a change of kernels (the
whole chain's spread compounds every stage's). Paths the
CPU lacks (avx512 without AVX-512) are left out. `native` is what torch, MKL and oneDNN pick by
themselves (on CPUs with AMX or AVX-512 this may differ from every named path). The first path
given is the reference for weight distances.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
DALI = ROOT / ".venv" / "bin" / "dali"

# one setting each of torch's own kernels, MKL (GEMM: linear layers) and oneDNN (convolutions)
KERNEL_PATHS = {
    "default": {"ATEN_CPU_CAPABILITY": "default", "MKL_CBWR": "COMPATIBLE", "ONEDNN_MAX_CPU_ISA": "SSE41"},
    "avx2": {"ATEN_CPU_CAPABILITY": "avx2", "MKL_CBWR": "AVX2", "ONEDNN_MAX_CPU_ISA": "AVX2"},
    "avx512": {"ATEN_CPU_CAPABILITY": "avx512", "MKL_CBWR": "AVX512", "ONEDNN_MAX_CPU_ISA": "AVX512_CORE"},
    "native": {},
}  # fmt: skip
KERNEL_ENV = ("ATEN_CPU_CAPABILITY", "MKL_CBWR", "ONEDNN_MAX_CPU_ISA")
# the artifacts of a tiny or demo run, by the row they give
EVAL_ROWS = {"source only": "iter0/eval", "PTSN only": "iter0/eval_ptsn", "x1": "iter1/eval"}
MODELS = {"pretrain": "iter0/model/model.pt", "retrain": "iter1/model/model.pt"}


def cpu_flags() -> set[str]:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("flags"):
                return set(line.split(":", 1)[1].split())
    except OSError:
        pass
    return set()


def available_paths(requested: list[str]) -> list[str]:
    """`requested` without the paths this CPU cannot run (avx2 needs AVX2, avx512 AVX-512F/BW/VL)."""
    flags = cpu_flags()
    needs = {"avx2": {"avx2", "fma"}, "avx512": {"avx512f", "avx512bw", "avx512vl", "avx512dq"}}
    return [path for path in requested if needs.get(path, set()) <= flags]


def path_env(path: str) -> dict[str, str]:
    """The environment of a run on kernel path `path`: this one's, without any kernel setting
    it had, plus the path's."""
    env = {k: v for k, v in os.environ.items() if k not in KERNEL_ENV and not k.startswith("MAKE")}
    return {**env, **KERNEL_PATHS[path]}


def run(command: list[str], env: dict, log: Path) -> float:
    """Run `command` (output to `log`), exit on failure; its wall time in seconds."""
    start = time.perf_counter()
    with log.open("w") as out:
        done = subprocess.run(command, cwd=ROOT, env=env, stdout=out, stderr=subprocess.STDOUT)
    if done.returncode:
        sys.exit(f"{' '.join(command)} failed ({done.returncode}); its output: {log}")
    return round(time.perf_counter() - start, 1)


def manifest_counts(directory: Path) -> dict:
    path = directory / "manifest.json"
    return json.loads(path.read_text())["outputs"].get("counts", {}) if path.exists() else {}


def eval_ap(directory: Path) -> dict | None:
    """AP_BEV / AP_3D @0.7 (all ranges) of an eval directory's metrics.json, or None."""
    path = directory / "metrics.json"
    if not path.exists():
        return None
    car = json.loads(path.read_text())["Car"]
    return {"bev": round(car["bev"]["all"], 2), "3d": round(car["3d"]["all"], 2)}


def chain_outputs(run_dir: Path) -> dict:
    """What a tiny or demo run's stages produced: ŝ, counts, AP per row."""
    scale_file = run_dir / "iter1" / "ptsn" / "scale.json"
    return {
        "scale": json.loads(scale_file.read_text())["scale"] if scale_file.exists() else None,
        "pseudo_boxes": manifest_counts(run_dir / "iter1" / "pseudo").get("boxes"),
        "rc_boxes": manifest_counts(run_dir / "iter1" / "rc").get("boxes_rc"),
        "cf_boxes": manifest_counts(run_dir / "iter1" / "cf").get("boxes_cf"),
        "ap": {row: eval_ap(run_dir / sub) for row, sub in EVAL_ROWS.items()},
    }


def weight_distance(a: Path, b: Path) -> float | None:
    """Relative L2 distance ||w_a - w_b|| / ||w_b|| over the float tensors of two checkpoints."""
    if not (a.exists() and b.exists()):
        return None
    import torch

    def weights(path):
        state = torch.load(path, map_location="cpu", weights_only=False)
        state = (
            state.get("state_dict", state.get("model", state)) if isinstance(state, dict) else state
        )
        return {
            k: v.double() for k, v in state.items() if torch.is_tensor(v) and v.is_floating_point()
        }

    wa, wb = weights(a), weights(b)
    diff = sum(float(((wa[k] - wb[k]) ** 2).sum()) for k in wb)
    norm = sum(float((wb[k] ** 2).sum()) for k in wb)
    return float((diff / norm) ** 0.5) if norm else None


def chain_variables(chain: str, run_dir: Path, threads: int, make_vars: list[str]) -> list[str]:
    """make's variables of a tiny or demo run into `run_dir` on `threads` torch threads."""
    if chain == "tiny":
        return [*make_vars, f"TINY_RUN={run_dir}", f"TINY_THREADS={threads}"]
    return [*make_vars, f"DEMO_RUN={run_dir}", f"DEMO_THREADS={threads}"]


def shown(path: str) -> str:
    """A run's directory as the results file names it: relative to the repository when inside
    it (the file is committed; a machine's own paths stay out of it)."""
    resolved = Path(path).resolve()
    return str(resolved.relative_to(ROOT)) if resolved.is_relative_to(ROOT) else path


def run_make_chain(chain: str, path: str, threads: int, runs: Path, make_vars: list[str]) -> dict:
    run_dir = runs / f"{chain}-{path}-t{threads}"
    variables = chain_variables(chain, run_dir, threads, make_vars)
    seconds = run(
        ["make", "--no-print-directory", chain, *variables],
        path_env(path),
        runs / f"{run_dir.name}.log",
    )
    return {"run": str(run_dir), "seconds": seconds, **chain_outputs(run_dir)}


def run_real_chain(args, path: str, threads: int, runs: Path) -> dict:
    """ptsn-sweep, pseudo-label and eval of `args.model` on `args.data` under `path`; eval at the
    model's own scale against `args.labels` (default: the frame set's boxes)."""
    out = runs / f"real-{path}-t{threads}"
    env, common = path_env(path), ["--threads", str(threads), "--no-progress"]
    seconds = run([str(DALI), "ptsn-sweep", "--model", args.model, "--data", args.data,
                   "--target-size", "sn", *common, "--out", str(out / "ptsn")],
                  env, runs / f"{out.name}-ptsn.log")  # fmt: skip
    seconds += run([str(DALI), "pseudo-label", "--model", args.model, "--data", args.data,
                    "--scale-from", str(out / "ptsn"), *common, "--out", str(out / "pseudo")],
                   env, runs / f"{out.name}-pseudo.log")  # fmt: skip
    labels = ["--gt", args.labels] if args.labels else []
    seconds += run([str(DALI), "eval", "--model", args.model, "--scale-from", args.model,
                    "--data", args.data, *labels, "--protocol", "kitti", "--iou", "0.7", *common,
                    "--out", str(out / "eval")], env, runs / f"{out.name}-eval.log")  # fmt: skip
    car = json.loads((out / "eval" / "metrics.json").read_text())["Car"]
    return {
        "run": str(out),
        "seconds": seconds,
        "scale": json.loads((out / "ptsn" / "scale.json").read_text())["scale"],
        "pseudo_boxes": manifest_counts(out / "pseudo").get("boxes"),
        "ap": {
            "model (moderate)": {
                "bev": round(car["bev"]["moderate"], 2),
                "3d": round(car["3d"]["moderate"], 2),
            }
        },  # fmt: skip
    }


# the stages `--isolate` reruns: their output under the run directory, and what is compared
ISOLATED = {
    "pretrain": "iter0/model",
    "ptsn-sweep": "iter1/ptsn",
    "eval (PTSN only)": "iter0/eval_ptsn",
    "pseudo-label": "iter1/pseudo",
    "ppcg-rc": "iter1/rc",
    "ppcg-cf": "iter1/cf",
    "retrain": "iter1/model",
}


def stage_commands(chain: str, variables: list[str], run_dir: Path) -> dict[str, str]:
    """The dali command line that writes each ISOLATED output of `run_dir`: make's plan of the
    chain (`make -n -B`, as if nothing were up to date)."""
    plan = subprocess.run(
        ["make", "-n", "-B", "--no-print-directory", chain, *variables],
        cwd=ROOT, env=path_env("native"), capture_output=True, text=True, check=True,
    ).stdout  # fmt: skip
    commands = {}
    for line in plan.splitlines():
        if not line.startswith(".venv/bin/dali "):
            continue
        for stage, sub in ISOLATED.items():
            if line.rstrip().endswith(f"--out {run_dir}/{sub}"):
                commands[stage] = line.rstrip()
    return commands


def stage_output(stage: str, out: Path, reference: Path) -> dict:
    """What one isolated stage wrote to `out`, against the reference run's `reference`."""
    if stage in ("pretrain", "retrain"):
        return {"weights_rel_distance": weight_distance(out / "model.pt", reference / "model.pt")}
    if stage == "ptsn-sweep":
        return {"scale": json.loads((out / "scale.json").read_text())["scale"]}
    if stage.startswith("eval"):
        return {"ap": eval_ap(out)}
    counts = manifest_counts(out)
    return {key: counts.get(key) for key in ("boxes", "boxes_rc", "boxes_cf") if key in counts}


def isolate_stages(reference: dict, paths: list[str], runs: Path, chain: str, make_vars) -> dict:
    """Each ISOLATED stage of the `reference` run rerun alone under every path of `paths`."""
    run_dir = Path(reference["run"])
    variables = chain_variables(chain, run_dir, reference["threads"], make_vars)
    commands = stage_commands(chain, variables, run_dir)
    if not commands:
        sys.exit(f"no stage command found in make's plan of {chain} for {run_dir}")
    results = {}
    for stage, command in commands.items():
        sub = ISOLATED[stage]
        results[stage] = {"reference": stage_output(stage, run_dir / sub, run_dir / sub)}
        for path in paths:
            out = runs / f"isolated-{run_dir.name}-{path}" / sub
            run(["bash", "-c", command.replace(f"--out {run_dir}/{sub}", f"--out {out}")],
                path_env(path), runs / f"isolated-{run_dir.name}-{path}-{stage.split()[0]}.log")  # fmt: skip
            results[stage][path] = stage_output(stage, out, run_dir / sub)
        print(stage, json.dumps(results[stage]), flush=True)
    return results


def spread(values: list) -> dict | None:
    """min, max, max - min and the largest relative deviation from the median of `values`."""
    values = [v for v in values if v is not None]
    if not values:
        return None
    ordered = sorted(values)
    median = ordered[len(ordered) // 2]
    rel = max(abs(v - median) for v in values) / abs(median) if median else None
    return {"min": min(values), "max": max(values), "range": max(values) - min(values),
            "max_rel_dev_from_median": None if rel is None else round(rel, 4)}  # fmt: skip


def summarize(results: list[dict]) -> dict:
    """The spread over every (path, threads) run of each stage's output."""
    summary = {
        key: spread([r[key] for r in results])
        for key in ("scale", "pseudo_boxes", "rc_boxes", "cf_boxes")
        if any(r.get(key) is not None for r in results)
    }
    rows = sorted({row for r in results for row, ap in r["ap"].items() if ap})
    for row in rows:
        for kind in ("bev", "3d"):
            summary[f"AP_{kind} {row}"] = spread(
                [(r["ap"].get(row) or {}).get(kind) for r in results]
            )
    for stage in MODELS:
        distances = [r.get("weights_rel_distance", {}).get(stage) for r in results]
        if any(d is not None for d in distances):
            summary[f"weights {stage}"] = spread(distances)
    return summary


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--chain", choices=("tiny", "demo", "real"), default="tiny")
    parser.add_argument("--paths", nargs="+", default=["native", "avx2", "avx512", "default"],
                        choices=list(KERNEL_PATHS))  # fmt: skip
    parser.add_argument("--threads", nargs="+", type=int, default=[1])
    parser.add_argument("--runs", type=Path, default=ROOT / "runs" / "numerical_stability")
    parser.add_argument("--model", default="models/kitti-hdl64e", help="real chain: the model")
    parser.add_argument("--data", help="real chain: an imported frame set")
    parser.add_argument("--labels", help="real chain: labels for eval (default: --data's boxes)")
    parser.add_argument("--out", type=Path)
    parser.add_argument("--isolate", action="store_true",
                        help="tiny, demo: also rerun each stage alone on the first path's inputs")  # fmt: skip
    parser.add_argument("make_vars", nargs="*", metavar="VAR=VALUE",
                        help="tiny, demo: variables for make (e.g. TINY_EPOCHS=12)")  # fmt: skip
    args = parser.parse_args()
    if args.chain == "real" and not args.data:
        parser.error("--chain real needs --data")
    paths = available_paths(args.paths)
    args.runs.mkdir(parents=True, exist_ok=True)
    results = []
    for threads in args.threads:
        for path in paths:
            load_before = round(os.getloadavg()[0], 2)
            if args.chain == "real":
                result = run_real_chain(args, path, threads, args.runs)
            else:
                result = run_make_chain(args.chain, path, threads, args.runs, args.make_vars)
            result.update(path=path, threads=threads, load_before=load_before,
                          load_after=round(os.getloadavg()[0], 2))  # fmt: skip
            results.append(result)
            print(json.dumps(result), flush=True)
    if args.chain != "real":
        reference = Path(results[0]["run"])
        for result in results:
            result["weights_rel_distance"] = {
                stage: weight_distance(Path(result["run"]) / model, reference / model)
                for stage, model in MODELS.items()
            }
    isolated = (
        isolate_stages(results[0], paths[1:], args.runs, args.chain, args.make_vars)
        if args.isolate and args.chain != "real"
        else None
    )
    import torch

    from dali_cli.runtime.machine import cpu_model

    document = {
        "chain": args.chain,
        "machine": {
            "cpu": cpu_model(),
            "cores": os.cpu_count(),
            "torch_capability": torch.backends.cpu.get_cpu_capability(),
            "amx": "amx_tile" in cpu_flags(),
        },  # fmt: skip
        "created": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "command": " ".join(sys.argv),
        "paths": {path: KERNEL_PATHS[path] for path in paths},
        "runs": [{**result, "run": shown(result["run"])} for result in results],
        "spread": summarize(results),
        "isolated_stages": isolated,
    }
    out = args.out or ROOT / "bench" / "results" / f"numerical_stability_{args.chain}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(document, indent=1) + "\n")
    print(json.dumps(document["spread"], indent=1))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
