#!/usr/bin/env bash
# The simulated flights of data-samples/scenarios/ over the project's synthetic
# map: a 64 x 64 km fractal terrain (8 m RGB ortho, 120 m DEM with 300 m of
# relief, UTM 13N, ellipsoidal heights), its landmark database, and one flight
# folder per scenario. Everything lands in target/sim-data/ and is reused
# when present.
# Usage: scripts/sim_samples.sh [SCENARIO_NAME ...] [-- extra trn simulate options, e.g. --duration 30]
set -euo pipefail
cd "$(dirname "$0")/.."
names=(); extra=()
while [ $# -gt 0 ]; do
  if [ "$1" = "--" ]; then shift; extra=("$@"); break; fi
  names+=("$1"); shift
done
[ ${#names[@]} -gt 0 ] || names=(balloon-nadir balloon-oblique rocket-ascent)
cargo build --release --quiet --bin trn
trn=target/release/trn
data=target/sim-data
mkdir -p "$data/flights"
if [ ! -f "$data/map.tif" ] || [ ! -f "$data/map-dem.tif" ]; then
  echo "== synthetic map: 8000 x 8000 px at 8 m (about a minute)"
  "$trn" synth --ortho "$data/map.part.tif" --dem "$data/map-dem.tif" --size 8000 --gsd 8 --seed 5 --relief 300 >/dev/null
  mv "$data/map.part.tif" "$data/map.tif"
fi
if [ ! -f "$data/map.gpkg" ]; then
  echo "== landmark database of the map"
  "$trn" build --ortho "$data/map.tif" --dem "$data/map-dem.tif" --dem-vertical ellipsoid --out "$data/map.gpkg" > "$data/map-build.json"
fi
for n in "${names[@]}"; do
  echo "== simulate $n"
  "$trn" simulate --ortho "$data/map.tif" --dem "$data/map-dem.tif" --dem-vertical ellipsoid \
    --scenario "data-samples/scenarios/$n.json" --out "$data/flights/$n" "${extra[@]}" > "$data/flights/$n.json"
  python3 -c "import json,sys; r=json.load(open(sys.argv[1])); print(f\"{r['out']}: {r['frames']} frames, {r['duration_s']:.0f} s, {r['height_start_m']:.0f} -> {r['height_end_m']:.0f} m, {r['render_ms_mean']:.0f} ms per frame\")" "$data/flights/$n.json"
done
