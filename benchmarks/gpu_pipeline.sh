#!/usr/bin/env bash
# Time and peak GPU memory of every stage of one target, each stage in its own process (as
# Snakemake runs them), GPU memory sampled with nvidia-smi every 100 ms.
# Usage: bash benchmarks/gpu_pipeline.sh <target> [--config file] [out.tsv]
set -euo pipefail
target=$1; shift
cfgarg=()
if [ "${1:-}" = "--config" ]; then cfgarg=(--config "$2"); shift 2; fi
out=${1:-benchmarks/out/gpu_pipeline_${target//\//_}.tsv}
mkdir -p "$(dirname "$out")"
echo -e "stage\tstep\tseconds\tpeak_gpu_mib" > "$out"
python3 -m physgs_steps.cli "${cfgarg[@]}" jobs "$target" | while read -r stage step; do
  [ "$stage" = "metrics" ] && continue
  mem=$(mktemp)
  nvidia-smi --query-gpu=memory.used --format=csv,noheader,nounits -lms 100 > "$mem" &
  smi=$!
  t0=$(date +%s.%N)
  python3 -m physgs_steps.cli "${cfgarg[@]}" stage "$stage" "$target" ${step:+--step "$step"} > "$mem.log" 2>&1 \
    || { tail -30 "$mem.log"; kill $smi; exit 1; }
  t1=$(date +%s.%N)
  kill $smi; wait $smi 2>/dev/null || true
  peak=$(sort -n "$mem" | tail -1)
  secs=$(awk -v a="$t0" -v b="$t1" 'BEGIN{printf "%.2f", b-a}')
  printf "%s\t%s\t%s\t%s\n" "$stage" "${step:--}" "$secs" "$peak" | tee -a "$out"
  grep -h -E "done in|UNSTABLE|stable," "$mem.log" | tail -2
  rm -f "$mem" "$mem.log"
done
