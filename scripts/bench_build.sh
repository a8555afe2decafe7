#!/usr/bin/env bash
# Builder throughput benchmark: `trn build` on a ~100-megapixel synthetic ortho
# (10000 x 10000 RGB, 1 m, tiled DEFLATE GeoTIFF like a USGS COG) against the
# time GDAL alone takes to read it (builder/examples/gdal_read.rs), as a ratio.
# Usage: scripts/bench_build.sh [SIZE_PX]   (default 10000; results also in
# target/bench-data/build_throughput.json)
set -euo pipefail
cd "$(dirname "$0")/.."
size=${1:-10000}
data=target/bench-data
mkdir -p "$data"
scripts/install-deps.sh
cargo build --release --quiet --bin trn -p trn -p trn-builder --example gdal_read
trn=target/release/trn
ortho="$data/synth-$size.tif"; dem="$data/synth-$size-dem.tif"
if [ ! -f "$ortho" ] || [ ! -f "$dem" ]; then
  echo "generating $ortho ..." >&2
  "$trn" synth --ortho "$ortho.part.tif" --dem "$dem" --size "$size" --gsd 1.0 --seed 11 >/dev/null
  mv "$ortho.part.tif" "$ortho"
fi
mp=$(python3 -c "print(round($size*$size/1e6, 1))")
# Warm the OS page cache once, then best of 3 for each.
read_s=$(target/release/examples/gdal_read "$ortho" 3)
best=""
for run in 1 2; do
  rm -f "$data/bench.gpkg"
  t0=$(date +%s.%N)
  TRN_LOG=warn /usr/bin/time -f "%M" -o "$data/rss-$run.txt" \
    "$trn" build --ortho "$ortho" --dem "$dem" --dem-vertical ellipsoid --out "$data/bench.gpkg" > "$data/report.json"
  t1=$(date +%s.%N)
  s=$(python3 -c "print(round($t1-$t0, 3))")
  if [ -z "$best" ] || python3 -c "import sys; sys.exit(0 if $s < $best else 1)"; then best=$s; fi
done
templates=$(python3 -c "import json; print(json.load(open('$data/report.json'))['templates'])")
rss_mb=$(python3 -c "print(round(max(int(open('$data/rss-%d.txt' % r).read().split()[-1]) for r in (1, 2)) / 1024))")
ratio=$(python3 -c "print(round($best/$read_s, 2))")
cores=$(nproc)
cat > "$data/build_throughput.json" <<JSON
{"megapixels": $mp, "cores": $cores, "gdal_read_s": $read_s, "build_s": $best, "ratio": $ratio, "templates": $templates, "peak_rss_mb": $rss_mb}
JSON
echo "raster: ${mp} MP RGB DEFLATE GeoTIFF, ${cores} cores"
echo "GDAL read (all bands, native type, best of 3): ${read_s} s"
echo "trn build (best of 2):                         ${best} s  -> ${templates} templates"
echo "ratio build / GDAL read:                       ${ratio}x  ($(python3 -c "print(round($mp/$best, 1))") MP/s)"
echo "peak resident memory of trn build:             ${rss_mb} MB"
