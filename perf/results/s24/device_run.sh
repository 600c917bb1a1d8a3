#!/bin/bash
# Session 24's GPU checks, run on the lent H200 after the kit's install (source /tmp/gpps-env.sh):
#   bash perf/results/s24/device_run.sh OUTDIR [tests|time|all]
# tests: the CUDA runs of the tests this session touched; time: the integration's pieces and the stage ablation.
out=${1:-$OUT}; what=${2:-all}
mkdir -p "$out"
filter() { grep -v "SyntaxWarning\|Save a field\|GppsWarning\|notes = self\|warnings.warn" ; }
if [ "$what" = tests ] || [ "$what" = all ]; then
  timeout 480 python -m pytest -q -p no:cacheprovider tests/test_integration_fused.py tests/test_ron_device.py \
    tests/test_reconstructor.py tests/test_clipping.py tests/test_stream_full.py tests/test_stream.py \
    -k "not cli and (not test_stream.py or convert or matches_batch)" 2>&1 | tail -25 > "$out/cuda_tests_s24.txt"
  tail -5 "$out/cuda_tests_s24.txt"
fi
if [ "$what" = time ] || [ "$what" = all ]; then
  python perf/results/s24/probe_integration_parts.py.txt cuda:0 256 2>&1 | filter | tail -14 | tee "$out/integration_parts_256_H200.json"
  python perf/reconstruct_ablation.py --size 256 --images 3 --device cuda:0 --repeat 5 --blocks 2 \
    --variants default,known,no-depth --out "$out/ablation_256x3_H200.json" 2>&1 | filter | tail -5
fi
