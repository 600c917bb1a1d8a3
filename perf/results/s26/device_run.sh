#!/bin/bash
# Session 26's GPU runs on the lent H200 after the kit's install (source /tmp/gpps-env.sh):
#   bash perf/results/s26/device_run.sh OUTDIR split|bench|tests26|solver|more|stream
out=${1:-$OUT}; what=${2:-split}
mkdir -p "$out"
filter() { grep -v "SyntaxWarning\|Save a field\|GppsWarning\|notes = self\|warnings.warn\|detect_clipping" ; }
if [ "$what" = split ]; then
  timeout 200 python perf/stream_frame_split.py --size 1024 --frames 60 --blocks 3 --device cuda:0 --variants default no-retry no-check split-subsets \
    --out "$out/stream_frame_split_1024_H200.json" 2>&1 | filter | tail -12 | tee "$out/stream_frame_split_1024_log.txt"
fi
if [ "$what" = split ] || [ "$what" = bench ]; then
  timeout 200 python perf/bench.py --device cuda:0 --sizes 1024 --repeat 20 2>&1 | filter | tail -30 > "$out/bench_1024_log.txt"
  tail -14 "$out/bench_1024_log.txt"; cp perf/results/bench_NVIDIA_H200.json "$out/" 2>/dev/null
fi
if [ "$what" = solver ]; then
  timeout 560 python -m pytest -q -p no:cacheprovider tests/test_solve_split.py tests/test_solver_lanes.py tests/test_solvers.py 2>&1 | tail -15 > "$out/cuda_tests_solver_s26.txt"
  tail -4 "$out/cuda_tests_solver_s26.txt"
fi
if [ "$what" = more ]; then
  timeout 560 python -m pytest -q -p no:cacheprovider tests/test_clipping.py tests/test_integration_fused.py \
    tests/test_integration_bini.py -k "not cli and (not test_integration_fused.py or persistent)" 2>&1 | tail -25 > "$out/cuda_tests_more_s26.txt"
  tail -5 "$out/cuda_tests_more_s26.txt"
fi
if [ "$what" = tests26 ]; then
  timeout 300 python -m pytest -q -p no:cacheprovider tests/test_solve_split.py tests/test_stream_retry.py \
    tests/test_stream_full.py tests/test_stream_recovery.py 2>&1 | tail -25 > "$out/cuda_tests_s26.txt"
  tail -4 "$out/cuda_tests_s26.txt"
fi
if [ "$what" = stream ]; then
  timeout 560 python -m pytest -q -p no:cacheprovider tests/test_stream.py tests/test_stream_retry.py tests/test_stream_full.py \
    tests/test_stream_recovery.py 2>&1 | tail -25 > "$out/cuda_tests_stream_s26.txt"
  tail -4 "$out/cuda_tests_stream_s26.txt"
fi
ls "$out"
