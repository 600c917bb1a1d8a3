#!/bin/bash
# The GPU runs of a session on the lent H200, after the kit's install (source /tmp/gpps-env.sh):
#   bash perf/device_run.sh OUTDIR tests|solvers|ablation|neighbour|gaps|bench|full|diligent|beforeafter|hostprof|usecache|cache
# Environment: T (a mode's time limit, s), MORE (more pytest arguments), TAG (a suffix of the output names),
# VARIANTS, BLOCKS, KT (ablation), PAIRS (beforeafter alternations), IR (diligent: --interreflections
# auto|off|subtract).  Sessions up to 28 kept a copy of this script in perf/results/sNN/ as their record; from
# session 29 the results README names the modes it ran.
out=${1:-$OUT}; what=${2:-tests}
mkdir -p "$out"
filter() { grep -v "SyntaxWarning\|Save a field\|GppsWarning\|notes = self\|warnings.warn\|detect_clipping" ; }
if [ "$what" = tests ]; then  # the stream and reconstructor files (MORE adds others)
  timeout ${T:-420} python -m pytest -q -p no:cacheprovider tests/test_solve_split.py tests/test_stream_full.py \
    tests/test_stream_retry.py tests/test_stream_recovery.py tests/test_reconstructor.py ${MORE:-} 2>&1 \
    | tail -40 > "$out/cuda_tests${TAG:-}.txt"
  tail -6 "$out/cuda_tests${TAG:-}.txt"
fi
if [ "$what" = solvers ]; then
  timeout ${T:-400} python -m pytest -q -p no:cacheprovider tests/test_solvers.py ${MORE:-} 2>&1 | tail -30 > "$out/cuda_tests_solvers${TAG:-}.txt"
  tail -6 "$out/cuda_tests_solvers${TAG:-}.txt"
fi
if [ "$what" = ablation ]; then
  timeout ${T:-400} python perf/reconstruct_ablation.py --size 256 --images 3 --device cuda:0 --repeat 5 --blocks ${BLOCKS:-2} \
    --variants "${VARIANTS:-default,warm-uncapped}" ${KT:---kernel-times} --out "$out/ablation_256x3_H200.json" 2>&1 | filter | tail -24
fi
if [ "$what" = neighbour ]; then
  timeout ${T:-300} python perf/neighbour_pass.py --size 256 --device cuda:0 --repeat 20 --blocks 3 --kernel-times \
    --out "$out/neighbour_pass_256_H200.json" 2>&1 | filter | tail -8
fi
if [ "$what" = diligent ]; then
  timeout ${T:-300} python perf/reconstruct_folder_timing.py .data/diligent/ball .data/diligent/bear --device cuda:0 --repeat 3 \
    ${IR:+--interreflections $IR} --out "$out/diligent_ball_bear${IR:+_$IR}_cuda0_H200.json" 2>&1 | filter | python -c "
import json, sys
for line in sys.stdin:
    try:
        r = json.loads(line); ir = r.get('interreflections') or {}
        print(r['folder'], r['call'], round(r['wall_s'], 3), round(r['maen_deg'], 4), {k: round(v, 3) for k, v in r['timings'].items()},
              {k: ir.get(k) for k in ('tau', 'indirect_share', 'negligible', 'skipped', 'round_seconds', 'why')})
    except Exception:
        pass"
fi
if [ "$what" = gaps ]; then
  timeout 240 python perf/idle_gaps.py --synthetic 256 --images 3 --device cuda:0 --warm 5 --reconstructor \
    --out "$out/idle_gaps_256x3_reconstructor_H200.json" 2>&1 | filter | tail -30 | tee "$out/idle_gaps_log.txt"
  timeout 120 python perf/stage_timeline.py --synthetic 256 --images 3 --device cuda:0 --repeat 3 \
    --out "$out/timeline_256x3_H200.json" 2>&1 | filter | tail -45 > "$out/timeline_log.txt"; tail -45 "$out/timeline_log.txt"
fi
if [ "$what" = bench ]; then
  timeout ${T:-220} python perf/bench.py --device cuda:0 --sizes 1024 --repeat 20 2>&1 | filter | tail -30 > "$out/bench_1024_log.txt"
  tail -14 "$out/bench_1024_log.txt"; cp perf/results/bench_NVIDIA_H200.json "$out/" 2>/dev/null
fi
if [ "$what" = full ]; then
  timeout ${T:-330} python perf/stream_full.py --size 1024 --frames 160 --timed 80 --device cuda:0 2>&1 | filter | tail -12 | tee "$out/stream_full_1024_log.txt"
  cp perf/results/stream_full_NVIDIA_H200.json "$out/" 2>/dev/null
fi
if [ "$what" = beforeafter ]; then  # an earlier tree (carried as .carry-old: its gpps and perf scripts) against
  # this tree, one process each, alternated on one machine (the lent hosts differ: only figures of one machine compare)
  for i in $(seq ${PAIRS:-2}); do
    for t in old new; do
      root=.; [ $t = old ] && root=.carry-old
      timeout 200 python $root/perf/reconstruct_ablation.py --size 256 --images 3 --device cuda:0 --repeat 7 --blocks 1 \
        --variants default --out "$out/ablation_${t}_$i.json" 2>&1 | filter | grep "^default" | sed "s/^/$t $i: /"
    done
  done
fi
if [ "$what" = usecache ]; then  # a kernel cache built here (perf/device_cache.py), carried: carry .kit/cache (the
  # directory) or .kit/cachexz (it as one tar.xz: tar cf - -C .kit/cache warp | xz > .kit/cachexz/warp_cache.tar.xz)
  mkdir -p "$WARP_CACHE_PATH"
  if [ -f .kit/cachexz/warp_cache.tar.xz ]; then
    xz -d < .kit/cachexz/warp_cache.tar.xz | tar x -C "$(dirname "$WARP_CACHE_PATH")"
  else
    cp -r .kit/cache/warp/* "$WARP_CACHE_PATH"/
  fi
  ls "$WARP_CACHE_PATH"/* | wc -l
fi
if [ "$what" = cache ]; then  # the Warp kernel cache this machine compiled, for a later session to carry
  (cd /tmp/gpps-cache && tar cf - warp | xz -T8 -6 | split -b 15M - "$out/warp_cache.tar.xz.part-")
  find /tmp/gpps-cache/warp -maxdepth 2 | head -5; du -sh /tmp/gpps-cache/warp
fi
ls -la "$out"
if [ "$what" = hostprof ]; then  # the host's functions in a warm 256^2 x 3 Reconstructor call (cProfile)
  timeout ${T:-200} python perf/profile_reconstruct.py --synthetic 256 --images 3 --device cuda:0 --reconstructor \
    --out "$out/host_profile_256x3_H200${TAG:-}" 2>&1 | filter | tail -40
fi
