#!/bin/bash
# Train the single-image network on the lent GPU machine, after the kit's install (source /tmp/gpps-env.sh):
#   bash training/device_train.sh OUTDIR data|start|wait
# data:  copy the carried Mitsuba shards (.mts_carry/*/mts_*.npz: training/mitsuba_random.py, packed with
#        pack_shard; one carried folder per call, each call within the 64 MiB the working tree may carry) to
#        /tmp/mts/train, and .mts_carry/val to /tmp/mts/val.
# start: unpack the carried Warp kernel cache (.kit/cachexz) when it is there, then run training/train_single.py
#        in its own process session (it outlives the call; the machine stays held while later calls wait) with
#        the recipe-v2 scenes rendered here and the Mitsuba shards; ARGS adds arguments (--minutes ...).
# wait:  wait up to T seconds (default 540) for the run to finish, then copy its weights, report and log to OUTDIR.
out=${1:-$OUT}; what=${2:-wait}
mkdir -p "$out" /tmp/mts/train /tmp/mts/val
if [ "$what" = data ]; then
  for d in .mts_carry/*/; do
    case "$d" in *val/) cp "$d"mts_*.npz /tmp/mts/val/ ;; *) cp "$d"mts_*.npz /tmp/mts/train/ ;; esac
  done
  echo "train shards: $(ls /tmp/mts/train | wc -l), val shards: $(ls /tmp/mts/val | wc -l)"
fi
if [ "$what" = start ]; then
  if [ -f .kit/cachexz/warp_cache.tar.xz ] && [ ! -d /tmp/gpps-cache/warp ]; then
    mkdir -p /tmp/gpps-cache && tar xJf .kit/cachexz/warp_cache.tar.xz -C /tmp/gpps-cache
  fi
  rm -rf /tmp/train-out && mkdir -p /tmp/train-out
  setsid nohup python3 training/train_single.py --out /tmp/train-out --mitsuba /tmp/mts/train --mitsuba-val /tmp/mts/val \
    ${ARGS:-} > /tmp/train-out/train.log 2>&1 < /dev/null &
  echo "started: pid $!"
  sleep ${T:-60}; tail -5 /tmp/train-out/train.log
fi
if [ "$what" = wait ]; then
  end=$(( $(date +%s) + ${T:-540} ))
  while [ ! -f /tmp/train-out/single_training.json ] && [ "$(date +%s)" -lt "$end" ]; do sleep 5; done
  tail -8 /tmp/train-out/train.log
  cp /tmp/train-out/train.log "$out/"
  [ -f /tmp/train-out/single_training.json ] && cp /tmp/train-out/single_net.npz /tmp/train-out/single_training.json "$out/"
  nvidia-smi --query-gpu=name,memory.used --format=csv,noheader
fi
