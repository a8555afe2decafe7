#!/usr/bin/env bash
# Landmarks in view at the true pose of every frame of the realistic
# scenarios (issue #12's density target): the server's own selection
# (`trn_navigator::view::landmarks_in_view`, the code behind /v1/footprint
# and /v1/coverage) run by `trn coverage --db` on a plan made of the flight's
# truth.csv poses and its camera.json. Per scenario and database: the
# median and the minimum over frames, and the share of frames with >= 60.
#
#   scripts/bench_footprint.sh            after scripts/bench_realistic.sh (its flights and
#                                         database DEMs in target/realistic/)
#
# Databases: the default build (target/realistic/db/WORLD.gpkg), and one built
# per scenario for its mission (`--camera camera.json --altitude MIN..MAX`, the
# flight's height range above the terrain; --max-off-nadir from the boresight),
# in target/realistic/footprint/.
# Environment: OUT (default target/realistic), THREADS (trn build, default 2).
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${OUT:-target/realistic}
trn=target/release/trn
[ -x "$trn" ] || cargo build --release --quiet --bin trn
suite="$OUT/suite.tsv"
[ -f "$suite" ] || { echo "no $suite: run scripts/bench_realistic.sh first" >&2; exit 1; }
work="$OUT/footprint"
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
import csv, json, math, os, sqlite3, sys
flight, db, plan = sys.argv[1:4]
cam = json.load(open(os.path.join(flight, "camera.json")))
rows = list(csv.DictReader(open(os.path.join(flight, "truth.csv"))))
poses = [{"lat_deg": float(r["lat"]), "lon_deg": float(r["lon"]), "h_m": float(r["h"]),
          "q_ecef_cam": [float(r[k]) for k in ("qw", "qx", "qy", "qz")]} for r in rows]
json.dump({"camera": cam, "poses": poses, "threshold": 60}, open(plan, "w"))
lat, lon = poses[0]["lat_deg"], poses[0]["lon_deg"]
con = sqlite3.connect(f"file:{db}?mode=ro", uri=True)
hs = sorted(r[0] for r in con.execute(
    "SELECT t.h_m FROM templates_rtree AS r CROSS JOIN templates AS t ON t.fid = r.id "
    "WHERE r.max_lon >= ? AND r.min_lon <= ? AND r.max_lat >= ? AND r.min_lat <= ?",
    (lon - 0.1, lon + 0.1, lat - 0.1, lat + 0.1)))
terrain = hs[len(hs) // 2] if hs else 0.0
off = 0.0
for p in poses:
    w, x, y, z = p["q_ecef_cam"]
    bz = (2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y))
    la, lo = math.radians(p["lat_deg"]), math.radians(p["lon_deg"])
    up = (math.cos(la) * math.cos(lo), math.cos(la) * math.sin(lo), math.sin(la))
    off = max(off, math.degrees(math.acos(max(-1.0, min(1.0, -sum(a * b for a, b in zip(bz, up)))))))
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
python3 - "$work/results.md" "${rows[@]}" <<'PY'
import json, sqlite3, statistics, sys
out, rows = sys.argv[1], sys.argv[2:]
lines = ["| scenario | database | templates | median in view | min in view | frames >= 60 |", "|---|---|---:|---:|---:|---:|"]
for r in rows:
    name, kind, path, db = r.split(" ")
    rep = json.load(open(path))
    n = [p["landmarks"] for p in rep["points"]]
    count = sqlite3.connect(f"file:{db}?mode=ro", uri=True).execute("SELECT sum(template_count) FROM trn_levels").fetchone()[0]
    lines.append(f"| {name} | {kind} | {count} | {statistics.median(n):.0f} | {min(n)} | {100 * sum(x >= 60 for x in n) / len(n):.0f}% |")
open(out, "w").write("\n".join(lines) + "\n")
print("\n".join(lines))
PY
