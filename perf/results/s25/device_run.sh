#!/bin/bash
# Session 25's GPU runs on the lent H200 after the kit's install (source /tmp/gpps-env.sh):
#   bash perf/results/s25/device_run.sh OUTDIR tests|stream|more
# tests: the CUDA runs of the stream tests this session touched; stream: perf/stream_full.py at 1024^2 and the
# bench's stream rows; more: the CUDA tests session 24 left unrun at its final tree (clipping, persistent tasks).
out=${1:-$OUT}; what=${2:-tests}
mkdir -p "$out"
filter() { grep -v "SyntaxWarning\|Save a field\|GppsWarning\|notes = self\|warnings.warn\|detect_clipping" ; }
if [ "$what" = tests ]; then
  timeout 400 python -m pytest -q -p no:cacheprovider tests/test_stream_retry.py tests/test_stream_full.py \
    tests/test_stream_recovery.py 2>&1 | tail -25 > "$out/cuda_tests_stream_s25.txt"
  tail -4 "$out/cuda_tests_stream_s25.txt"
  timeout 200 python -m pytest -q -p no:cacheprovider tests/test_stream.py -k "convert or matches_batch or persistent" \
    2>&1 | tail -15 > "$out/cuda_tests_stream_py_s25.txt"
  tail -4 "$out/cuda_tests_stream_py_s25.txt"
fi
if [ "$what" = stream ]; then
  timeout 330 python perf/stream_full.py --size 1024 --frames 160 --timed 80 --device cuda:0 2>&1 | filter | tail -12 | tee "$out/stream_full_1024_log.txt"
  cp perf/results/stream_full_NVIDIA_H200.json "$out/" 2>/dev/null
  timeout 200 python perf/bench.py --device cuda:0 --sizes 1024 --repeat 20 2>&1 | filter | tail -30 > "$out/bench_1024_log.txt"
  tail -12 "$out/bench_1024_log.txt"; cp perf/results/bench_NVIDIA_H200.json "$out/" 2>/dev/null
fi
if [ "$what" = known ]; then
  timeout 200 python perf/stream_known_ablation.py --size 1024 --frames 60 --blocks 3 --device cuda:0 --out "$out/stream_known_ablation_1024_H200.json" 2>&1 | filter | tail -5
  timeout 330 python -m pytest -q -p no:cacheprovider tests/test_stream_retry.py tests/test_stream_full.py \
    tests/test_stream_recovery.py 2>&1 | tail -25 > "$out/cuda_tests_stream_s25.txt"
  tail -4 "$out/cuda_tests_stream_s25.txt"
fi
if [ "$what" = solver ]; then
  timeout 400 python -m pytest -q -p no:cacheprovider tests/test_solver_lanes.py tests/test_solvers.py -x 2>&1 | tail -15 > "$out/cuda_tests_solver_s25.txt"
  tail -4 "$out/cuda_tests_solver_s25.txt"
fi
if [ "$what" = more ]; then
  timeout 560 python -m pytest -q -p no:cacheprovider tests/test_clipping.py tests/test_integration_fused.py \
    tests/test_integration_bini.py -k "not cli and (not test_integration_fused.py or persistent)" 2>&1 | tail -25 > "$out/cuda_tests_more_s25.txt"
  tail -5 "$out/cuda_tests_more_s25.txt"
fi
ls "$out"
