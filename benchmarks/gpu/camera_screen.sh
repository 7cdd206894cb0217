#!/bin/bash
# A camera-student recipe screened on a lent GPU machine in one call: demonstrations on its CPU cores (one
# shard per process), BC on the GPU (device=cuda, two seeds at once), then the training-range circuits screen and
# hairpins (a TRAINING track) on its cores. Selection data only: nothing here drives set:heldout.
# Run from the repository root with the cp312 wheels in .whl (see run_device.sh), OUT set, the device tool carrying [.whl]:
#   set -o pipefail; CAM="env.camera.width=160 env.camera.height=96" bash benchmarks/gpu/camera_screen.sh 2>&1 | tee $OUT/log.txt
# CAM: the camera overrides of the recipe (passed to demos and train). NS shards of FR frames; DRY=1: a local dry run
# (tiny sizes, device=cpu). TD, TB, TE: the stages' time limits [s] (demos, BC, screen).
CAM=${CAM:-}
source "$(dirname "$0")/_lib.sh" /tmp/cs_work

sec "A. setup"
if [ "$DRY" != 1 ]; then
  install_wheels .whl
  NS=${NS:-14}; FR=${FR:-7200}; DEV=cuda; STEPS=${STEPS:-15000}; WK=14; LAPS=10
else
  export PYTHONPATH=$PWD
  NS=2; FR=300; DEV=cpu; STEPS=20; WK=2; LAPS=1
fi
nproc; nvidia-smi --query-gpu=name,memory.total --format=csv,noheader 2>&1 | head -1
echo "CAM=$CAM NS=$NS FR=$FR STEPS=$STEPS"
COMMON="experiment=camera_distill env.camera.renderer=tiny $CAM"

sec "B. demonstrations: $NS shards x $FR frames"
for i in $(seq 1 $NS); do
  timeout ${TD:-300} python3 -m torcsrl.demos $COMMON demos.frames=$FR demos.out=$W/shard$i seed=$((100 + i)) threads=1 \
    hydra.run.dir=$W/hd$i > $W/demo$i.log 2>&1 &
done
wait
tail -2 $W/demo1.log
SH=$(ls -d $W/shard*/ 2>/dev/null | sed 's:/$::' | paste -sd, -)
echo "shards: $(ls -d $W/shard*/ | wc -l); off-road episodes:"; grep -h -o "[0-9]* of [0-9]* episodes ended off[^;,.]*" $W/demo*.log | head -3

sec "C. BC on $DEV, seeds 0 and 1 at once ($STEPS steps)"
for s in 0 1; do
  timeout ${TB:-420} python3 -m torcsrl.train $COMMON seed=$s demos.path=[$SH] demos.frames=0 demos.dagger_rounds=0 \
    algo.bc_steps=$STEPS device=$DEV threads=2 run_dir=$W/bc$s progress=false eval.per_track=false eval.env.track=oval \
    eval.max_steps=200 hydra.run.dir=$W/hb$s > $W/bc$s.log 2>&1 &
done
wait
for s in 0 1; do tail -3 $W/bc$s.log; done
CK=""
for s in 0 1; do
  c=$(ls $W/bc$s/checkpoints/ckpt_*.pt 2>/dev/null | tail -1)
  [ -n "$c" ] && { cp $c $OUT/bc$s.pt; CK="$CK $c"; }
done
echo "checkpoints:$CK"

sec "D. circuits screen (proc-10001..8, 2 laps, asphalt) + hairpins asphalt $LAPS laps"
timeout ${TE:-300} python3 benchmarks/generalisation.py --screen --generator proc --no-bundled --laps 2 --surfaces asphalt \
  --policy $CK --workers $WK --out $W/scr > $W/scr.log 2>&1 &
for c in $CK; do
  n=$(basename $(dirname $(dirname $c)))
  timeout ${TE:-300} python3 -m torcsrl.evaluate --policy $c --track hairpins --surface asphalt --laps $LAPS > $W/hp_$n.log 2>&1 &
done
wait
tail -8 $W/scr.log
for f in $W/hp_*.log; do echo "== $f"; grep -v "^pybullet\|Warning\|warn" $f | tail -12; done
cp $W/scr/generalisation.json $OUT/ 2>/dev/null
tar czf $OUT/logs.tgz -C $W $(cd $W && ls *.log) 2>/dev/null
echo "DONE $(el)"
