#!/bin/bash
# The CUDA check (docs/scale-out.md, "On a GPU"): run on a machine with an NVIDIA GPU and a
# python3 that has a CUDA torch, from the repository root, with the wheels of dali's other
# dependencies in .whl/ (no network needed) or already installed:
#   bash bench/gpu_check.sh OUT_DIR
# 1. the demo's two DALI iterations (`make iter2`, 48/48 frames, seed 0) with DEVICE=cuda: every
#    model stage (pretrain, ptsn-sweep, pseudo-label, retrain, eval) on the GPU, per-frame stages
#    on 8 local workers; 2. one pretraining under torchrun (NPROC=1: DDP with nccl);
#    3. training frames/s, data-wait share and GPU utilisation with 0 and 8 loader workers,
#    and the time of each stage of the chain; 4. the test suite, where `--device auto` now means
#    the GPU (and tests/test_box_ops.py compares the GPU's IoU and NMS with numpy); 5. the
#    refiner's point crop on the GPU vs numpy (bench/refine_crop.py). Writes OUT_DIR/log.txt (what it
#    printed), iter2.log, ddp.log, pytest.log, refine_crop.json, report.md (`dali report` of the demo run) and
#    gpu_check.tar.gz (the run's manifests and metrics, and the logs).
set -uo pipefail
OUT=${1:?usage: bash bench/gpu_check.sh OUT_DIR}
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1
exec > >(tee "$OUT/log.txt") 2>&1
# scratch outside the checkout: installed wheels, a venv-shaped folder and the demo run
SCRATCH=$(mktemp -d)
date -u; nvidia-smi -L; nproc; lscpu | grep 'Model name'
if ls .whl/*.whl > /dev/null 2>&1; then
    python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
        --target "$SCRATCH/site" .whl/*.whl || exit 1
    export PYTHONPATH=$SCRATCH/site:$PWD
else
    export PYTHONPATH=$PWD
fi
python3 -c 'import torch; print("torch", torch.__version__, "cuda", torch.version.cuda, torch.cuda.get_device_name(0))'
# a venv-shaped folder for the Makefile: its dali, python and torchrun are this python3's
V=$SCRATCH/venv
mkdir -p $V/bin
printf '#!%s\nfrom dali_cli.cli import main\nif __name__ == "__main__":\n    main()\n' "$(command -v python3)" > $V/bin/dali
ln -sf "$(command -v python3)" $V/bin/python
printf '#!/bin/sh\nexec python3 -m torch.distributed.run "$@"\n' > $V/bin/torchrun
chmod +x $V/bin/dali $V/bin/torchrun
touch $V/.installed
RUN=$SCRATCH/demo
status=0
start=$(date +%s)
make --no-print-directory iter2 VENV=$V RUN=$RUN FRAMES=48 EPOCHS=6 SEED=0 DEVICE=cuda \
    WORKERS=8 SYNTH_WORKERS=8 > "$OUT/iter2.log" 2>&1 || { status=1; echo "make iter2 FAILED"; tail -n 30 "$OUT/iter2.log"; }
echo "make iter2 on cuda: $(( $(date +%s) - start )) s"
# time per stage of the chain (each manifest's timings, seconds)
find $RUN -name manifest.json | sort | while read -r m; do
    python3 -c 'import json, sys; m = json.load(open(sys.argv[1]))
t = m.get("timings", {}); total = sum(v for v in t.values() if isinstance(v, (int, float)))
print(f"stage {m.get(\"stage\", \"?\"):14s} {total:8.1f} s  {sys.argv[1]}")' "$m"
done
# training throughput: frames/s, the data-wait share and the GPU's utilisation, with the
# batches made in the training process (0 loader workers) and in 8 loader workers
for workers in 0 8; do
    nvidia-smi --query-gpu=utilization.gpu,memory.used --format=csv,noheader,nounits -lms 500 \
        > "$OUT/util-w$workers.csv" 2> /dev/null &
    smi=$!
    start=$(date +%s)
    $V/bin/dali pretrain --source $RUN/data/source --epochs 2 --batch-size 8 --device cuda \
        --seed 0 --loader-workers $workers --no-progress --force --out $RUN/speed-w$workers/model \
        > "$OUT/speed-w$workers.log" 2>&1 || { status=1; tail -n 30 "$OUT/speed-w$workers.log"; }
    kill $smi 2> /dev/null
    python3 -c 'import json, sys
import pyarrow.parquet as pq
d, util = sys.argv[1], sys.argv[2]
train = json.load(open(d + "/model.json"))["train"]
log = pq.read_table(d + "/train_log.parquet").to_pylist()[1:]
wait = sum(r.get("data_wait_share", 0) for r in log) / max(1, len(log))
rows = [line.split(",") for line in open(util) if line.strip()]
busy = [float(r[0]) for r in rows]
print(f"loader workers {sys.argv[3]}: {train[\"frames_per_s\"]} frames/s, data wait {wait:.0%}, "
      f"GPU busy {sum(busy) / max(1, len(busy)):.0f} % (mean of {len(busy)} samples)")' \
        $RUN/speed-w$workers/model "$OUT/util-w$workers.csv" $workers || status=1
    echo "pretrain batch 8, $workers loader workers: $(( $(date +%s) - start )) s"
done
# the refiner's point crop on the GPU against numpy's on the CPU (same points, time per frame)
python3 bench/refine_crop.py --data $RUN/data/target --device cuda > "$OUT/refine_crop.json" 2>&1 \
    || { status=1; echo "refine crop FAILED"; tail -n 20 "$OUT/refine_crop.json"; }
python3 -m dali_cli.cli report $RUN > "$OUT/report.md" 2>&1 || status=1
start=$(date +%s)
$V/bin/torchrun --standalone --nproc-per-node 1 $V/bin/dali pretrain --source $RUN/data/source \
    --epochs 2 --device cuda --seed 0 --out $RUN/ddp/model > "$OUT/ddp.log" 2>&1 \
    || { status=1; echo "torchrun pretraining FAILED"; tail -n 30 "$OUT/ddp.log"; }
echo "torchrun (nccl) pretraining of 96 frames: $(( $(date +%s) - start )) s"
start=$(date +%s)
timeout 240 python3 -m pytest -q -x -p no:cacheprovider -n 8 -k 'not ray' tests > "$OUT/pytest.log" 2>&1
rc=$?
echo "pytest rc $rc in $(( $(date +%s) - start )) s: $(tail -n 1 "$OUT/pytest.log")"
find $RUN -name manifest.json -o -name 'metrics*.json' | tar czf "$OUT/gpu_check.tar.gz" -T - "$OUT"/*.log 2> /dev/null
for m in $RUN/iter0/model $RUN/iter2/model $RUN/ddp/model; do  # where each training ran, how fast
    python3 -c 'import json, sys; m = json.load(open(sys.argv[1] + "/manifest.json"))
print(sys.argv[1], m["runtime"], m["timings"], m["outputs"]["counts"])' $m
done
exit $status
