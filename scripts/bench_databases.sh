#!/usr/bin/env bash
# Issue #12's database benchmarks on the realistic scenarios, after
# scripts/bench_realistic.sh (its flights and database DEMs in target/realistic/):
#
# 1. Landmarks in view at the true pose of every frame: the server's own
#    selection (`trn_view::landmarks_in_view`, the code behind
#    /v1/footprint and /v1/coverage) run by `trn coverage --db` on a plan made of
#    the flight's truth.csv poses and its camera.json. Per scenario and
#    database: the median and the minimum over frames, and the share of frames
#    with >= 60.
# 2. trn navigate on each database (both flights of a pair at once, one per
#    core): fix share, mean / p95 / worst 3D error of accepted fixes, the
#    mean NEES of the fixes against its 95% band, and the farthest fix from
#    the truth in its own covariance's sigmas (`trn evaluate`'s consistency).
#
# Databases:
#   default   the default build (target/realistic/db/WORLD.gpkg)
#   mission   one per scenario for its mission (`--camera camera.json --altitude
#             MIN..MAX`, the flight's height range above the terrain;
#             --max-off-nadir from the boresight)
#   sun       one per world with every scenario's sun baked in (`--sun AZ,EL`
#             for each distinct sun of its scenarios); each flight navigates
#             with `--sun` set to its own
# Results in target/realistic/databases/results.md.
#
#   scripts/bench_databases.sh
# Environment: OUT (default target/realistic), THREADS (trn build, default 2),
#   NAV_ARGS (more trn navigate options, e.g. --no-inertial-focal), RESULTS
#   (the results file's name in OUT/databases/, default results.md; with
#   another name the runs' folders go to OUT/databases/<name without .md>/).
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${OUT:-target/realistic}
source scripts/realistic_suite.sh
work="$OUT/databases"
mkdir -p "$work"
rows=()
while IFS=$'\t' read -r name flight db ortho dem opts; do
  read -r -a opt_arr <<< "$opts"
  read -r -a ortho_arr <<< "$ortho"
  read -r -a dem_arr <<< "$dem"
  plan="$work/$name-plan.json"
  # The plan, and the mission: heights above the terrain (the default database's
  # median template height within 0.1 deg of the start) and the boresight's
  # largest angle from the vertical.
  mission=$(python3 - "$flight" "$db" "$plan" <<'PY'
import csv, json, math, os, sys
sys.path.insert(0, "scripts")
from benchlib import boresight_cos_from_vertical, terrain_height
flight, db, plan = sys.argv[1:4]
cam = json.load(open(os.path.join(flight, "camera.json")))
rows = list(csv.DictReader(open(os.path.join(flight, "truth.csv"))))
poses = [{"lat_deg": float(r["lat"]), "lon_deg": float(r["lon"]), "h_m": float(r["h"]),
          "q_ecef_cam": [float(r[k]) for k in ("qw", "qx", "qy", "qz")]} for r in rows]
json.dump({"camera": cam, "poses": poses, "threshold": 60}, open(plan, "w"))
terrain = terrain_height(db, poses[0]["lat_deg"], poses[0]["lon_deg"])
off = 0.0
for p in poses:
    c = boresight_cos_from_vertical(p["q_ecef_cam"], p["lat_deg"], p["lon_deg"])
    off = max(off, math.degrees(math.acos(max(-1.0, min(1.0, c)))))
hs = [p["h_m"] - terrain for p in poses]
print(f"{max(min(hs), 100.0):.0f}..{max(max(hs), 100.0):.0f} {min(off, 89.0):.1f}")
PY
)
  read -r alt off <<< "$mission"
  mdb="$work/$name-mission.gpkg"
  if [ ! -f "$mdb" ] || [ "$flight/camera.json" -nt "$mdb" ]; then
    echo "== $name: mission database (--altitude $alt --max-off-nadir $off)" >&2
    "$trn" build --ortho "${ortho_arr[@]}" --dem "${dem_arr[@]}" "${opt_arr[@]}" --camera "$flight/camera.json" \
      --altitude "$alt" --max-off-nadir "$off" --threads "${THREADS:-2}" --out "$mdb" > "$work/$name-mission-build.json" 2>/dev/null
  fi
  for kind in default mission; do
    d=$db; [ $kind = mission ] && d=$mdb
    "$trn" coverage --db "$d" --plan "$plan" > "$work/$name-$kind-coverage.json"
    rows+=("$name $kind $work/$name-$kind-coverage.json $d")
  done
done < "$suite"

# Sun databases: per world, every distinct sun of its scenarios.
declare -A sun_db
while IFS=$'\t' read -r name flight db ortho dem opts; do
  w=${db##*/}; w=${w%.gpkg}
  [ -n "${sun_db[$w]:-}" ] && continue
  read -r -a opt_arr <<< "$opts"
  read -r -a ortho_arr <<< "$ortho"
  read -r -a dem_arr <<< "$dem"
  suns=$(awk -F'\t' -v d="$db" '$3 == d {print $1}' "$suite" | while read -r n; do
    python3 -c "import json,sys; s=json.load(open(sys.argv[1]))['realism']['sun']; print('%g,%g,%g' % (s['azimuth_deg'], s['elevation_deg'], s.get('ambient', 0.25)))" \
      "data-samples/scenarios/realistic/$n.json"; done | sort -u)
  sdb="$work/$w-sun.gpkg"
  sun_args=(); for s in $suns; do sun_args+=(--sun "$s"); done
  if [ ! -f "$sdb" ] || [ "$db" -nt "$sdb" ]; then
    echo "== $w: sun database (${sun_args[*]})" >&2
    "$trn" build --ortho "${ortho_arr[@]}" --dem "${dem_arr[@]}" "${opt_arr[@]}" "${sun_args[@]}" \
      --threads "${THREADS:-2}" --out "$sdb" > "$work/$w-sun-build.json" 2>/dev/null
  fi
  sun_db[$w]=$sdb
done < "$suite"

# Navigation on every database kind.
jobs="$work/nav-jobs.txt"
# The runs' folders: OUT/databases/nav-* for the default results file, else
# OUT/databases/<its name without .md>/nav-*, so a variant (NAV_ARGS with
# its own RESULTS) does not overwrite the default's runs.
label=${RESULTS:-results.md}
label=${label%.md}
navdir=$work
[ "$label" = results ] || navdir="$work/$label"
mkdir -p "$navdir"
: > "$jobs"
while IFS=$'\t' read -r name flight db ortho dem opts; do
  w=${db##*/}; w=${w%.gpkg}
  sun=$(python3 -c "import json,sys; s=json.load(open(sys.argv[1]))['realism']['sun']; print('%g,%g,%g' % (s['azimuth_deg'], s['elevation_deg'], s.get('ambient', 0.25)))" \
    "data-samples/scenarios/realistic/$name.json")
  echo "$name default $flight $db" >> "$jobs"
  echo "$name mission $flight $work/$name-mission.gpkg" >> "$jobs"
  echo "$name sun $flight ${sun_db[$w]} --sun $sun" >> "$jobs"
done < "$suite"
navigate() {
  read -r name kind flight db extra <<< "$1"
  local o="$navdir/nav-$name-$kind"
  # Nothing of an earlier run left to be read as this one's.
  rm -rf "$o" "$o.json" "$o.log" "$o.eval.json"
  # A folder per run: matches.csv and covariance.csv are written next to
  # poses.csv, and `trn evaluate` reads them there (two runs at once must not
  # share them).
  mkdir -p "$o"
  # shellcheck disable=SC2086
  "$trn" navigate --db "$db" --flight "$flight" --out "$o/poses.csv" $extra ${NAV_ARGS:-} > "$o.json" 2> "$o.log"
  "$trn" evaluate --flight "$flight" --poses "$o/poses.csv" --json "$o.eval.json" > /dev/null 2>&1
}
export -f navigate; export trn navdir NAV_ARGS
echo "== navigating $(wc -l < "$jobs") flight/database pairs" >&2
tr '\n' '\0' < "$jobs" | xargs -0 -P 2 -I{} bash -c 'navigate "$1"' _ {}

python3 - "$work/${RESULTS:-results.md}" "$navdir" "${rows[@]}" <<'PY'
import json, os, sqlite3, statistics, sys
out, navdir, rows = sys.argv[1], sys.argv[2], sys.argv[3:]
def count(db):
    return sqlite3.connect(f"file:{db}?mode=ro", uri=True).execute("SELECT sum(template_count) FROM trn_levels").fetchone()[0]
lines = ["| scenario | database | templates | median in view | min in view | frames >= 60 |", "|---|---|---:|---:|---:|---:|"]
names = []
for r in rows:
    name, kind, path, db = r.split(" ")
    if name not in names:
        names.append(name)
    rep = json.load(open(path))
    n = [p["landmarks"] for p in rep["points"]]
    lines.append(f"| {name} | {kind} | {count(db)} | {statistics.median(n):.0f} | {min(n)} | {100 * sum(x >= 60 for x in n) / len(n):.0f}% |")
lines += ["", "| scenario | database | trn fix | mean m | p95 m | worst m | mean NEES | NEES band | farthest fix (sigma) |", "|---|---|---:|---:|---:|---:|---:|---|---:|"]
for name in names:
    for kind in ("default", "mission", "sun"):
        ev = os.path.join(navdir, f"nav-{name}-{kind}.eval.json")
        if not os.path.exists(ev):
            lines.append(f"| {name} | {kind} | failed | | | | | | |")
            continue
        r = json.load(open(ev))["runs"][0]
        e = r["fix_errors"]["pos_m"]
        f = lambda k: "–" if e.get(k) is None else f"{e[k]:.1f}"
        c = r.get("consistency") or {}
        nees = "–" if "mean_nees" not in c else f"{c['mean_nees']:.2f}"
        band = "–" if "band" not in c else f"{c['band'][0]:.2f}–{c['band'][1]:.2f}"
        far = "–" if "max_sigma_distance" not in c else f"{c['max_sigma_distance']:.1f}"
        lines.append(f"| {name} | {kind} | {100 * r['status']['share_fix']:.0f}% | {f('mean')} | {f('p95')} | {f('max')} | {nees} | {band} | {far} |")
open(out, "w").write("\n".join(lines) + "\n")
print("\n".join(lines))
PY
