#!/usr/bin/env bash
# The seed spread of several architectures at once on one GPU node, then their CUDA inference speed.
#
# One GPU runs small models far below its capacity, so every (architecture, seed) trains and is
# evaluated in a bench/seed_spread.py process of its own, all side by side (each with CPU threads
# of its own), under a time limit; then seed_spread.py --summarise-only gathers each
# architecture's finished runs into its spread (a run cut short by the limit is left out). Then
# bench/inference_benchmark.py --device cuda times every model with the first seed's trained
# weights (accuracy of each path on the test split; BENCH_DEVICE=cpu times the CPU instead, none
# skips it). Needs only the training stack (PyTorch,
# torchvision, pyarrow, scipy, scikit-image, pyyaml): give it a config that
# `seed_spread.py --write-config` wrote where Snakemake is installed, and a results folder with
# the datasets (e.g. from bench/shrink_results.py).
#
#   bench/gpu_seed_spread.sh CONFIG.json RESULTS OUT SECONDS "ARCH ..." SEED ...
#   bench/gpu_seed_spread.sh .carry/paper_gpu.json .carry/results_paper_cpu /tmp/gpu 420 \
#       "resnet50 inception_v3 efficientnet_b0" 2025 2026 2027
#
# Writes OUT/<arch>/spread.{md,json}, OUT/<arch>-<seed>.log, OUT/benchmark.{txt,json}.
set -u
usage() { sed -n '2,19p' "$0" >&2; exit 2; }
[ $# -ge 6 ] || usage
config=$1 results=$2 out=$3 seconds=$4 archs=$5
shift 5
[ -n "${archs// /}" ] || usage
case $seconds in
    ''|*[!0-9]*) whole=0 ;;
    *) whole=$((10#$seconds)) ;;
esac
[ "$whole" -gt 0 ] || { echo "SECONDS must be a whole number of seconds above 0, got '$seconds'" >&2; usage; }
here=$(cd "$(dirname "$0")/.." && pwd)
export PYTHONPATH="$here/src${PYTHONPATH:+:$PYTHONPATH}" PYTHONUNBUFFERED=1
py=${PYTHON:-python3}
n=$(( $(echo "$archs" | wc -w) * $# ))
threads=$(( ($(nproc) - 1) / n ))
[ "$threads" -ge 1 ] || threads=1
mkdir -p "$out" || exit 2
echo "$(date -u +%FT%TZ) $n runs side by side, $threads CPU threads each, ${seconds} s at most"
for arch in $archs; do
    for seed in "$@"; do
        timeout "$seconds" "$py" "$here/bench/seed_spread.py" --config "$config" --no-snakemake --results "$results" \
            --archs "$arch" --seed-list "$seed" --out "$out/runs/$arch-$seed" --threads "$threads" \
            > "$out/$arch-$seed.log" 2>&1 &
    done
done
wait
for arch in $archs; do
    echo "== $arch"
    "$py" "$here/bench/seed_spread.py" --config "$config" --no-snakemake --results "$results" --archs "$arch" \
        --seed-list "$@" --out "$out/$arch" --summarise-only 2>&1 | grep -v "^\s*$" | tail -n 6
done
if [ "${BENCH_DEVICE:-cuda}" = none ]; then
    echo "$(date -u +%FT%TZ) done (no benchmark: BENCH_DEVICE=none)"
    exit 0
fi
models=$(mktemp -d)
trap 'rm -rf "$models"' EXIT
for arch in $archs; do  # the first seed's model of each, where the layout of inference_benchmark --results
    m="$results/seed_spread/$1/$arch/model.pt"
    [ -f "$m" ] && mkdir -p "$models/models/$arch" && ln -s "$(cd "$(dirname "$m")" && pwd)/model.pt" "$models/models/$arch/"
done
for ds in "$results"/*/manifest; do
    ln -s "$(cd "$(dirname "$ds")" && pwd)" "$models/$(basename "$(dirname "$ds")")"
done
"$py" "$here/bench/inference_benchmark.py" --device "${BENCH_DEVICE:-cuda}" --archs $archs --seconds 1 --repeats 3 \
    --results "$models" --json "$out/benchmark.json" > "$out/benchmark.txt" 2>&1
cat "$out/benchmark.txt" | grep -v "^\s*$" | tail -n 12
echo "$(date -u +%FT%TZ) done"
