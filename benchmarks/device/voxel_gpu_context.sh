#!/usr/bin/env bash
# Issue 28, the voxel model's next lever on a GPU machine: larger crops (more context for the outdoor gaps)
# against the shipped crop size at equal time, side by side, then whole-map Table III of the validation scenes
# for both (the crops' own validation F1 is not comparable across crop sizes); no test scene is read.
# Results: $OUT/ctx/{c96,c144}/ (histories, val tables). Locally: DEV=cpu TL=20 W=1 OUT=/tmp/o bash <this>.
set -u
DEV=${DEV:-cuda}; TL=${TL:-150}; W=${W:-7}; M=${M:-.maps/coloradar_maps}; OUT=${OUT:?set OUT}
export PYTHONUNBUFFERED=1 PYTHONPATH=${PYTHONPATH:-}:.
R=$OUT/ctx; mkdir -p $R/c96 $R/c144
tv() { python3 -m stages.complete.train_voxel --maps $M --device $DEV --workers $W --batch-size 8 \
       --time-limit $TL --val-every 250 "$@"; }
tv --out $R/c96/v96.safetensors > $R/c96/log.txt 2>&1 &
tv --out $R/c144/v144.safetensors --crop-xy 144 > $R/c144/log.txt 2>&1 &
wait
for k in c96 c144; do
  python3 -m stages.complete.voxel_table3 --maps $M --device $DEV --split val --checkpoint $R/$k/*.safetensors \
    --out $R/$k/val > $R/$k/val.log 2>&1 &
done
wait
rm -f $R/*/*.state.pt $R/*/*.png $R/*/*.safetensors $R/*/val.md
grep -h -E "Overall" $R/c96/val.log $R/c144/val.log; tail -n 2 $R/c96/log.txt $R/c144/log.txt
