#!/usr/bin/env bash
# Issue 28 on a GPU machine (the `device` tool's H200): the voxel model trained for TL seconds at the shipped
# architecture and at a larger one side by side (each with its own crop workers), then Table III on the
# validation scenes (the union decision) and the 18 test scenes for both, and the shipped CPU checkpoint's
# inference timed on the GPU. Results in $OUT/results.tgz. Locally: DEV=cpu TL=20 W=1 OUT=/tmp/o bash <this>.
set -u
DEV=${DEV:-cuda}; TL=${TL:-270}; W=${W:-7}; M=${M:-.maps/coloradar_maps}; OUT=${OUT:?set OUT}
export PYTHONUNBUFFERED=1 PYTHONPATH=${PYTHONPATH:-}:.
R=$OUT/r; mkdir -p $R/a $R/b
T0=$(date +%s)
say() { echo "[$(( $(date +%s) - T0 )) s] $*" | tee -a $R/log.txt; }
say "start on $DEV"; (nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv || true) >> $R/log.txt 2>&1
python3 -c "import torch; print('torch', torch.__version__, torch.cuda.is_available())" >> $R/log.txt 2>&1
tv() { python3 -m stages.complete.train_voxel --maps $M --device $DEV --workers $W --batch-size 8 \
       --time-limit $TL --val-every 400 "$@"; }
tv --out $R/a/rmap_voxel_gpu.safetensors > $R/train_a.log 2>&1 &
tv --out $R/b/rmap_voxel_gpu_wide.safetensors --widths 16,32,64,96,128 > $R/train_b.log 2>&1 &
wait
say "trained: $(tail -c 300 $R/train_a.log | tr '\n' ' ') | $(tail -c 300 $R/train_b.log | tr '\n' ' ')"
t3() { python3 -m stages.complete.voxel_table3 --maps $M --device $DEV "$@"; }
t3 --split test --checkpoint data/models/rmap_voxel.safetensors --out $R/shipped_test > $R/shipped_test.log 2>&1
say "shipped checkpoint, test, $DEV: $(tail -n 2 $R/shipped_test.log | tr '\n' ' ')"
for k in a b; do
  c=$(ls $R/$k/*.safetensors)
  (t3 --split val --checkpoint $c --decide-union --out $R/${k}_val > $R/${k}_val.log 2>&1 &&
   t3 --split test --checkpoint $c --out $R/${k}_test > $R/${k}_test.log 2>&1) &
done
wait
say "tables done"
rm -f $R/*/*.state.pt
tar czf $OUT/results.tgz -C $OUT r && say "packed $(du -sh $OUT/results.tgz)"
