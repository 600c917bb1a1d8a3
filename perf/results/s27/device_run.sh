#!/bin/bash
# Session 27's GPU runs on the lent H200 after the kit's install (source /tmp/gpps-env.sh):
#   bash perf/results/s27/device_run.sh OUTDIR gaps|bench|full|tests|tests2|ablation|diligent|verify|neighbour
out=${1:-$OUT}; what=${2:-gaps}
mkdir -p "$out"
filter() { grep -v "SyntaxWarning\|Save a field\|GppsWarning\|notes = self\|warnings.warn\|detect_clipping" ; }
if [ "$what" = gaps ]; then
  timeout 240 python perf/idle_gaps.py --synthetic 256 --images 3 --device cuda:0 --warm 5 --reconstructor \
    --out "$out/idle_gaps_256x3_reconstructor_H200.json" 2>&1 | filter | tail -30 | tee "$out/idle_gaps_log.txt"
  timeout 120 python perf/stage_timeline.py --synthetic 256 --images 3 --device cuda:0 --repeat 3 \
    --out "$out/timeline_256x3_H200.json" 2>&1 | filter | tail -45 > "$out/timeline_log.txt"; tail -45 "$out/timeline_log.txt"
fi
if [ "$what" = bench ]; then
  timeout 220 python perf/bench.py --device cuda:0 --sizes 1024 --repeat 20 2>&1 | filter | tail -30 > "$out/bench_1024_log.txt"
  tail -14 "$out/bench_1024_log.txt"; cp perf/results/bench_NVIDIA_H200.json "$out/" 2>/dev/null
fi
if [ "$what" = full ]; then
  timeout 330 python perf/stream_full.py --size 1024 --frames 160 --timed 80 --device cuda:0 2>&1 | filter | tail -12 | tee "$out/stream_full_1024_log.txt"
  cp perf/results/stream_full_NVIDIA_H200.json "$out/" 2>/dev/null
fi
if [ "$what" = tests ]; then
  timeout 280 python -m pytest -q -p no:cacheprovider tests/test_solve_split.py tests/test_stream_retry.py \
    tests/test_stream_full.py tests/test_stream_recovery.py tests/test_clipping.py 2>&1 | tail -25 > "$out/cuda_tests_s27.txt"
  tail -4 "$out/cuda_tests_s27.txt"
fi
if [ "$what" = tests2 ]; then
  timeout ${T:-280} python -m pytest -q -p no:cacheprovider tests/test_solve_split.py tests/test_clipping.py ${MORE:-} 2>&1 \
    | tail -40 > "$out/cuda_tests_s27_b.txt"
  tail -6 "$out/cuda_tests_s27_b.txt"
fi
if [ "$what" = ablation ]; then
  timeout 400 python perf/reconstruct_ablation.py --size 256 --images 3 --device cuda:0 --repeat 5 --blocks 2 \
    --variants "${VARIANTS:-default}" --out "$out/ablation_256x3_H200.json" 2>&1 | filter | tail -20
fi
if [ "$what" = diligent ]; then
  timeout 300 python perf/reconstruct_folder_timing.py .data/diligent/ball .data/diligent/bear --device cuda:0 --repeat 3 \
    --out "$out/diligent_ball_bear_cuda0_H200.json" 2>&1 | filter | python -c "
import json, sys
for line in sys.stdin:
    try:
        r = json.loads(line); print(r['folder'], r['call'], round(r['wall_s'], 3), round(r['maen_deg'], 4), {k: round(v, 3) for k, v in r['timings'].items()})
    except Exception:
        pass"
  timeout 200 python perf/reconstruct_ablation.py --size 256 --images 3 --device cuda:0 --repeat 5 --blocks 1 --variants default \
    --kernel-times --out "$out/ablation_256x3_kernels_H200.json" 2>&1 | filter | tail -4
fi
if [ "$what" = verify ]; then
  timeout 130 python -m pytest -q -p no:cacheprovider tests/test_integration.py tests/test_ron_device.py 2>&1 | tail -12 > "$out/cuda_tests_integration_ron_device.txt"
  tail -2 "$out/cuda_tests_integration_ron_device.txt"
  timeout 130 python -m pytest -q -p no:cacheprovider tests/test_reconstructor.py tests/test_front.py 2>&1 | tail -12 > "$out/cuda_tests_reconstructor_front.txt"
  tail -2 "$out/cuda_tests_reconstructor_front.txt"
  timeout ${T:-200} python -m pytest -q -p no:cacheprovider tests/test_solvers.py 2>&1 | tail -12 > "$out/cuda_tests_solvers.txt"
  tail -2 "$out/cuda_tests_solvers.txt"
fi
if [ "$what" = neighbour ]; then  # (written after this session's device time was spent: for the next session)
  timeout 300 python perf/neighbour_pass.py --size 256 --device cuda:0 --repeat 20 --blocks 3 --kernel-times \
    --out "$out/neighbour_pass_256_H200.json" 2>&1 | filter | tail -5
fi
ls "$out"
