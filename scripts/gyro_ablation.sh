#!/usr/bin/env bash
# Gyro ablation (as in IBAL's balloon flight report): the same flight navigated
# at 4 Hz and 2 Hz image rates, with and without gyro propagation, and the
# share of each altitude segment processed successfully (rows with status fix).
# Usage: scripts/gyro_ablation.sh [FLIGHT_DIR] [BAND_M]
#   default flight: target/sim-data/flights/balloon-nadir (scripts/sim_samples.sh),
#   default segments of 1000 m. Results in target/ablation/<flight>/.
set -euo pipefail
cd "$(dirname "$0")/.."
flight=${1:-target/sim-data/flights/balloon-nadir}
band=${2:-1000}
db=${DB:-target/sim-data/map.gpkg}
out=target/ablation/$(basename "$flight")
mkdir -p "$out"
cargo build --release --quiet --bin trn
trn=target/release/trn
args=()
for rate in 4 2; do
  for gyro in gyro no-gyro; do
    label="${rate}hz-$gyro"
    extra=(); [ "$gyro" = no-gyro ] && extra=(--no-gyro)
    mkdir -p "$out/$label"
    TRN_LOG=warn "$trn" navigate --db "$db" --flight "$flight" --out "$out/$label/poses.csv" --rate "$rate" "${extra[@]}" > /dev/null
    args+=(--poses "$out/$label/poses.csv" --label "$label")
  done
done
TRN_LOG=warn "$trn" evaluate --flight "$flight" "${args[@]}" --band-m "$band" --json "$out/eval.json" > "$out/eval.txt"
# The comparison table is the last block of the report.
sed -n '/^== share of each run/,$p' "$out/eval.txt"
