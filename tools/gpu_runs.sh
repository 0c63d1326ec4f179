#!/usr/bin/env bash
# On a lent GPU machine, in the repository root, with what tools/gpu_bundle.sh wrote carried
# along: bench/gpu.py once per variant on one input (rendered once), each run's table copied
# to OUT as it ends, so a call cut off by its time limit still returns the runs it finished.
#   DEADLINE=SECONDS tools/gpu_runs.sh OUT FRAMES VARIANT...
# A VARIANT is a comma-separated list of `cusfm map --set` settings ("-" for none), e.g.
#   DEADLINE=170 tools/gpu_runs.sh $OUT 300 - features.matcher.lightglue.half_precision=false,seed=1
# Writes OUT/machine.txt, OUT/run<N>.md and OUT/run<N>.json (N: the variant's position).
set -u
out=$1 frames=$2
shift 2
deadline=${DEADLINE:-540}
start=$SECONDS
left() { echo $((deadline - (SECONDS - start))); }
mkdir -p "$out"
{ nvidia-smi -L; nproc; date -u; git log --oneline -1; } > "$out/machine.txt" 2>&1
# shellcheck source=tools/gpu_env.sh
source tools/gpu_env.sh || { echo "tools/gpu_env.sh failed" | tee -a "$out/machine.txt"; exit 1; }
work=$(mktemp -d)
n=0
for variant in "$@"; do
  n=$((n + 1))
  if [ "$(left)" -lt 30 ]; then echo "variant $n ($variant): no time left" >> "$out/machine.txt"; break; fi
  mkdir -p "$work/$n"
  [ $n -gt 1 ] && ln -s "$work/1/inputs" "$work/$n/inputs"  # the input, rendered once
  sets=()
  if [ "$variant" != "-" ]; then
    IFS=, read -ra kvs <<< "$variant"
    for kv in "${kvs[@]}"; do sets+=(--set "$kv"); done
  fi
  timeout "$(left)" python bench/gpu.py --out "$work/$n" --frames "$frames" --devices cuda \
    --features aliked "${sets[@]}" > "$work/$n.log" 2>&1
  echo "variant $n ($variant): rc $? at $((SECONDS - start)) s" >> "$out/machine.txt"
  cp "$work/$n/gpu.md" "$out/run$n.md" 2>/dev/null || tail -20 "$work/$n.log" > "$out/run$n.md"
  cp "$work/$n/gpu.json" "$out/run$n.json" 2>/dev/null
done
cat "$out/machine.txt" "$out"/run*.md
