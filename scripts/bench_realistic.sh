#!/usr/bin/env bash
# The realistic navigation benchmark: real relief, real imagery, and a world
# that is not the map. One command from a fresh clone: installs what is
# missing (scripts/install-deps.sh, the Python venv), fetches the real worlds, degrades each world's DEM
# for its database, builds trn's databases with DEFAULT options, renders every
# scenario of data-samples/scenarios/realistic/ with the true DEM, then runs
# scripts/bench_nav.sh (trn navigate and the OpenCV baseline, each on its own
# core, the baseline on its own database sized for the camera) and prints the
# table.
#
# Worlds (data-samples/fetch.sh says where each file comes from):
#   sierra    SRTM of the eastern Sierra Nevada (3000 m of relief, slopes to
#             66 deg) under a Landsat 7 scene of Utah (draped: the imagery is
#             not of that place; its baked-in shading does not match the relief)
#   saltlake  Landsat 7 of the Great Salt Lake's south shore (water, ponds,
#             salt and mud flats) over a flat SRTM patch (draped)
# The database of each world is built from a degraded copy of its DEM (trn
# degrade-dem: 160 m cells, twice the SRTM spacing, correlated noise of DB_NOISE_M RMS over 600 m);
# the camera sees the original. Each scenario also has its own sun, a camera
# spectral response, tone curve and brightness field unlike the ortho, haze,
# noise, blur, calibration and clock errors (camera_error) and, for one, a
# 3 km / 300 m / 5 deg initial error: see the scenario files.
#
# Usage: scripts/bench_realistic.sh [SCENARIO_NAME ...]
# Environment:
#   OUT=target/realistic      worlds' databases in OUT/db/, flights in OUT/flights/, bench in OUT/bench/
#   DURATION=                 cut every flight to this many seconds (default: whole scenarios)
#   DB_NOISE_M=4              RMS of the database DEM's noise (m)
#   REBUILD=1                 rebuild databases and flights even when present
#   plus bench_nav.sh's (CORE_TRN, CORE_OCV, NAV_ARGS, TRN_ARGS, BASELINE_ARGS, PY)
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${OUT:-target/realistic}
DB_NOISE_M=${DB_NOISE_M:-4}
scen_dir=data-samples/scenarios/realistic
real=data-samples/real

scripts/install-deps.sh
data-samples/fetch.sh >/dev/null
scripts/venv.sh >/dev/null
cargo build --release --quiet --bin trn
trn=target/release/trn
mkdir -p "$OUT/db" "$OUT/flights"

# world -> ortho, rendered DEM, build options
source scripts/realistic_worlds.sh
opts=$world_opts
read -r -a opt_arr <<< "$opts"

world_of() { case "$1" in sierra-*) echo sierra ;; saltlake-*) echo saltlake ;; *) echo "$1: unknown world" >&2; exit 1 ;; esac; }

names=("$@")
if [ ${#names[@]} -eq 0 ]; then
  for f in "$scen_dir"/*.json; do names+=("$(basename "$f" .json)"); done
fi

for w in sierra saltlake; do
  db_dem="$OUT/db/$w-db-dem.tif"
  if [ -n "${REBUILD:-}" ] || [ ! -f "$db_dem" ]; then
    echo "== $w: database DEM (160 m, ${DB_NOISE_M} m correlated noise)" >&2
    "$trn" degrade-dem --dem "${dem[$w]}" --out "$db_dem" --cell-m 160 --noise-m "$DB_NOISE_M" \
      --noise-scale-m 600 --seed 7 > "$OUT/db/$w-db-dem.json"
  fi
  if [ -n "${REBUILD:-}" ] || [ ! -f "$OUT/db/$w.gpkg" ]; then
    echo "== $w: trn build (default options)" >&2
    "$trn" build --ortho "${ortho[$w]}" --dem "$db_dem" "${opt_arr[@]}" --out "$OUT/db/$w.gpkg" \
      > "$OUT/db/$w-build.json"
  fi
done

suite="$OUT/suite.tsv"
: > "$suite"
for n in "${names[@]}"; do
  w=$(world_of "$n")
  f="$OUT/flights/$n"
  if [ -n "${REBUILD:-}" ] || [ ! -f "$f/frames.csv" ] || [ "$scen_dir/$n.json" -nt "$f/frames.csv" ]; then
    echo "== simulate $n" >&2
    dur=(); [ -n "${DURATION:-}" ] && dur=(--duration "$DURATION")
    "$trn" simulate --ortho "${ortho[$w]}" --dem "${dem[$w]}" "${opt_arr[@]}" \
      --scenario "$scen_dir/$n.json" --out "$f" "${dur[@]}" > "$OUT/flights/$n.json"
  fi
  printf '%s\t%s\t%s\t%s\t%s\t%s\n' "$n" "$f" "$OUT/db/$w.gpkg" "${ortho[$w]}" "$OUT/db/$w-db-dem.tif" "$opts" >> "$suite"
done

SUITE="$suite" OUT="$OUT/bench" scripts/bench_nav.sh
