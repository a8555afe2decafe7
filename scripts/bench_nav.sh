#!/usr/bin/env bash
# Navigator benchmark: trn navigate against the OpenCV baseline
# (scripts/baseline_opencv.py) on the same flights, in the same run, both at
# once, each pinned to its own core, both scored by trn evaluate against the
# flight's truth.csv.
#
# Usage: scripts/bench_nav.sh [FLIGHT_DIR ...]
#        SUITE=suite.tsv scripts/bench_nav.sh
#   default: every flight folder in target/sim-data/flights/ (scripts/sim_samples.sh),
#   with DB, ORTHO, DEM and BUILD_ARGS below.
#   SUITE: one scenario per line, tab-separated (blank lines and lines starting
#   with # are skipped):
#     name<TAB>flight_dir<TAB>trn_db<TAB>ortho<TAB>dem<TAB>extra_build_args
#   trn_db is the database trn navigate uses; ortho and dem (several files:
#   separated by spaces) are what the baseline's own database is built from,
#   with extra_build_args (may be empty, e.g. "--dem-vertical egm96 --ortho-bands 3,2,1").
#   The DEM a database is built from may differ from the one the flight was
#   rendered from (that is the point of a realistic scenario).
# Environment:
#   DB=target/sim-data/map.gpkg        trn's database (without SUITE)
#   ORTHO=target/sim-data/map.tif      \ the baseline database's sources (without SUITE)
#   DEM=target/sim-data/map-dem.tif    /
#   BUILD_ARGS="--dem-vertical ellipsoid"  extra trn build options (without SUITE)
#   OUT=target/bench-nav               results: OUT/<name>/{trn,opencv}/poses.csv (+ matches.csv),
#                                      OUT/<name>/eval.{json,txt}, OUT/<name>/baseline-db.json,
#                                      OUT/results.{md,json}; baseline databases in OUT/baseline-db/
#                                      (reused when the same sources and options come again)
#   CORE_TRN=0, CORE_OCV=1             the cores trn navigate and the baseline are pinned to (taskset)
#   PY=.venv/bin/python                Python with numpy + opencv-python-headless
#   BUILD_THREADS=2                    trn build --threads for the baseline databases
#   NAV_ARGS=, TRN_ARGS=, BASELINE_ARGS=  extra options: NAV_ARGS to both (e.g. "--rate 2" or
#                                      "--no-gyro"), TRN_ARGS to trn navigate only, BASELINE_ARGS
#                                      to the baseline only (e.g. "--ncc interior")
#
# The baseline's own database ("what a competent engineer would build for this
# camera"): `trn build --ortho O --dem D [extra] --template-size S
# --min-template-size S --spacing S --max-relief 1000 --max-hidden 1 --levels N
# --min-contrast 6 --min-shi-tomasi 2`
# (one template size, GSD doubling per level, no relief or occlusion test; the
# texture thresholds fixed at trn build's defaults before stop 51, so the
# baseline is the one every earlier figure was measured against),
# where, from camera.json (width, height, fx),
# init.json (height, boresight) and the mission's altitude range:
#   altitude range: the balloon's start_h_m/end_h_m from the flight's
#     scenario.json, else the min/max height of truth.csv (the mission plan's
#     altitude profile, known in advance; nothing else is read from it), always
#     together with init.json's height; above the terrain height (median
#     height of the baseline's own DEM within 0.1 deg of the init position,
#     made ellipsoidal by the DEM's datum: --dem-vertical in the extra build
#     options, EGM96 when they do not say; until stop 52 it was the median
#     template height of trn's database there, which moved with trn's defaults);
#   incidence i: angle of init.json's boresight from the local vertical (<= 70 deg);
#   image GSD at height H above the terrain: g(H) = H / cos i / fx / sqrt(cos i);
#   typical GSD g_typ = g(geometric mean of the lowest and highest height);
#   target template span T = clamp(min(width, height) / 6, 20, 32) image pixels;
#   S = clamp(round(T * min(g_typ / ortho GSD, 1)), 8, 32): at the database level
#     fitting the image a template spans ~T pixels; when the camera resolves
#     finer than the ortho, level 0 templates get fewer pixels so they still
#     span ~T image pixels;
#   spacing S (one landmark per template-sized cell: dense);
#   G = max(64, 12 * g(highest)): coarse levels for the coarse pyramid search;
#   N = 1 + floor(log2(G / base)) levels (1..12), base being the ortho GSD
#   rounded up to three digits (trn build's level-0 GSD): GSDs up to G.
# The ortho GSD is read with gdalinfo (degrees converted at the ortho's centre).
#
# Prints, per scenario and for both: mean / p95 3D position error over accepted
# fixes, fix share over all frames, the worst error of an accepted fix, median
# ms per frame (poses.csv `ms`), and the ratios trn / opencv (error and time:
# lower is better; fix share: higher is better).
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${OUT:-target/bench-nav}
CORE_TRN=${CORE_TRN:-0}
CORE_OCV=${CORE_OCV:-1}
PY=${PY:-.venv/bin/python}
BUILD_THREADS=${BUILD_THREADS:-2}
read -r -a nav_args <<< "${NAV_ARGS:-}"
read -r -a trn_args <<< "${TRN_ARGS:-}"
read -r -a base_args <<< "${BASELINE_ARGS:-}"

# Scenarios: parallel arrays.
names=(); flights=(); dbs=(); orthos=(); dems=(); extras=()
if [ -n "${SUITE:-}" ]; then
  [ -f "$SUITE" ] || { echo "$SUITE: no suite file" >&2; exit 1; }
  while IFS=$'\t' read -r n f d o m x || [ -n "${n:-}" ]; do
    case "$n" in ''|'#'*) continue ;; esac
    [ -n "${f:-}" ] && [ -n "${d:-}" ] && [ -n "${o:-}" ] && [ -n "${m:-}" ] \
      || { echo "$SUITE: '$n': needs name, flight_dir, trn_db, ortho, dem (tab-separated)" >&2; exit 1; }
    names+=("$n"); flights+=("$f"); dbs+=("$d"); orthos+=("$o"); dems+=("$m"); extras+=("${x:-}")
  done < "$SUITE"
else
  DB=${DB:-target/sim-data/map.gpkg}
  ORTHO=${ORTHO:-target/sim-data/map.tif}
  DEM=${DEM:-target/sim-data/map-dem.tif}
  BUILD_ARGS=${BUILD_ARGS-"--dem-vertical ellipsoid"}
  fl=("$@")
  if [ ${#fl[@]} -eq 0 ]; then
    for d in target/sim-data/flights/*/; do
      [ -f "$d/frames.csv" ] && fl+=("${d%/}")
    done
  fi
  [ ${#fl[@]} -gt 0 ] || { echo "no flights (run scripts/sim_samples.sh first)" >&2; exit 1; }
  for f in "${fl[@]}"; do
    names+=("$(basename "${f%/}")"); flights+=("${f%/}"); dbs+=("$DB"); orthos+=("$ORTHO"); dems+=("$DEM"); extras+=("$BUILD_ARGS")
  done
fi
[ ${#names[@]} -gt 0 ] || { echo "no scenarios" >&2; exit 1; }
for i in "${!names[@]}"; do
  [ -f "${flights[$i]}/frames.csv" ] || { echo "${flights[$i]}: not a flight folder" >&2; exit 1; }
  [ -f "${dbs[$i]}" ] || { echo "${dbs[$i]}: no landmark database (run scripts/sim_samples.sh first)" >&2; exit 1; }
done
[ -x "$PY" ] || { echo "$PY: no Python (run scripts/venv.sh)" >&2; exit 1; }
"$PY" -c "import cv2, numpy" || { echo "$PY lacks opencv-python-headless / numpy" >&2; exit 1; }

cargo build --release --quiet --bin trn
trn=target/release/trn
pin_trn=(); pin_ocv=()
if command -v taskset >/dev/null; then pin_trn=(taskset -c "$CORE_TRN"); pin_ocv=(taskset -c "$CORE_OCV"); fi
mkdir -p "$OUT/baseline-db"

# The template-size rule (see the comment above): prints "S N" and writes the details as JSON.
choose_db() { # flight json_out dem_vertical "ortho..." "dem..."
  "$PY" - "$@" <<'EOF'
import csv, json, math, os, subprocess, sys
sys.path.insert(0, "scripts")
from benchlib import boresight_cos_from_vertical, dem_terrain_height
flight, jout, vertical = sys.argv[1], sys.argv[2], sys.argv[3]
orthos, dems = sys.argv[4].split(), sys.argv[5].split()
cam = json.load(open(os.path.join(flight, "camera.json")))
init = json.load(open(os.path.join(flight, "init.json")))
w, h, fx = int(cam["width"]), int(cam["height"]), float(cam["fx"])
lat, lon = float(init["lat"]), float(init["lon"])
heights, source = [float(init["h"])], "init.json"
sc = os.path.join(flight, "scenario.json")
traj = (json.load(open(sc)).get("trajectory") or {}) if os.path.exists(sc) else {}
if traj.get("kind") == "balloon" and "start_h_m" in traj and "end_h_m" in traj:
    heights += [float(traj["start_h_m"]), float(traj["end_h_m"])]
    source = "init.json + scenario.json"
elif os.path.exists(os.path.join(flight, "truth.csv")):
    hs = [float(r["h"]) for r in csv.DictReader(open(os.path.join(flight, "truth.csv")))]
    if hs:
        heights += [min(hs), max(hs)]
        source = "init.json + truth.csv altitude range"
terrain = dem_terrain_height(dems, lat, lon, vertical)
# Boresight incidence from init.json's attitude.
cos_i = max(boresight_cos_from_vertical(init["q_ecef_cam"], lat, lon), math.cos(math.radians(70.0)))
def gsd(agl):
    return agl / cos_i / fx / math.sqrt(cos_i)
agl_lo, agl_hi = max(min(heights) - terrain, 100.0), max(max(heights) - terrain, 100.0)
g_typ, g_hi = gsd(math.sqrt(agl_lo * agl_hi)), gsd(agl_hi)
# Ortho GSD (the coarsest of the files), metres.
ortho_gsd = 0.0
for o in orthos:
    info = json.loads(subprocess.run(["gdalinfo", "-json", o], check=True, capture_output=True, text=True).stdout)
    gt = info["geoTransform"]
    px = max(abs(gt[1]), abs(gt[5]))
    wkt = (info.get("coordinateSystem") or {}).get("wkt", "")
    if wkt.startswith("GEOG") or (px < 0.01 and not wkt.startswith("PROJ")):
        cy = gt[3] + gt[5] * info["size"][1] / 2
        px = max(abs(gt[1]) * 111320.0 * math.cos(math.radians(cy)), abs(gt[5]) * 110574.0)
    ortho_gsd = max(ortho_gsd, px)
T = min(max(min(w, h) / 6.0, 20.0), 32.0)
S = int(min(max(round(T * min(g_typ / ortho_gsd, 1.0)), 8), 32))
G = max(64.0, 12.0 * g_hi)
mag = 10 ** (math.floor(math.log10(ortho_gsd)) - 2)
base = math.ceil(ortho_gsd / mag - 1e-9) * mag
N = max(1, min(12, 1 + math.floor(math.log2(G / base) + 1e-9)))
json.dump({"heights_m": [min(heights), max(heights)], "heights_from": source, "terrain_h_m": terrain,
           "terrain_from": f"median of the DEM within 0.1 deg ({vertical} heights made ellipsoidal)",
           "incidence_deg": math.degrees(math.acos(cos_i)), "image_gsd_typ_m": g_typ, "image_gsd_high_m": g_hi,
           "ortho_gsd_m": ortho_gsd, "target_px": T, "template_size": S, "spacing": S, "max_gsd_m": G, "levels": N},
          open(jout, "w"), indent=2)
print(S, N)
EOF
}

bases=()
for i in "${!names[@]}"; do
  name=${names[$i]}; f=${flights[$i]}; db=${dbs[$i]}
  o="$OUT/$name"
  rm -rf "$o"; mkdir -p "$o/trn" "$o/opencv"
  read -r -a ortho_files <<< "${orthos[$i]}"
  read -r -a dem_files <<< "${dems[$i]}"
  read -r -a extra <<< "${extras[$i]}"
  vertical=egm96  # trn build's DEM datum for these sources: --dem-vertical in the extra options, else EGM96
  for k in "${!extra[@]}"; do [ "${extra[$k]}" = --dem-vertical ] && vertical=${extra[$((k + 1))]:-egm96}; done
  rule=$(choose_db "$f" "$o/baseline-db.json" "$vertical" "${orthos[$i]}" "${dems[$i]}") \
    || { echo "$name: template-size rule failed" >&2; exit 1; }
  read -r S N <<< "$rule"
  build=(--ortho "${ortho_files[@]}" --dem "${dem_files[@]}" "${extra[@]}" --template-size "$S" --min-template-size "$S"
         --spacing "$S" --max-relief 1000 --max-hidden 1 --levels "$N" --min-contrast 6 --min-shi-tomasi 2)
  key=$(printf '%s\n' "${build[@]}" | sha1sum | cut -c1-12)
  base="$OUT/baseline-db/$key.gpkg"
  if [ ! -f "$base" ]; then
    echo "== $name: baseline database: template size $S, spacing $S, $N levels -> $base" >&2
    "$trn" build "${build[@]}" --threads "$BUILD_THREADS" --out "$base" > "$OUT/baseline-db/$key.json"
    printf '%s\n' "${build[@]}" > "$OUT/baseline-db/$key.args"
  else
    echo "== $name: baseline database $base (reused)" >&2
  fi
  bases+=("$base")
  echo "== $name: trn navigate (core $CORE_TRN) and the OpenCV baseline (core $CORE_OCV), at once" >&2
  "${pin_trn[@]}" "$trn" navigate --db "$db" --flight "$f" --out "$o/trn/poses.csv" \
    "${nav_args[@]}" "${trn_args[@]}" > "$o/trn/report.json" 2> "$o/trn/log.txt" &
  pid_trn=$!
  "${pin_ocv[@]}" "$PY" scripts/baseline_opencv.py --db "$base" --flight "$f" --out "$o/opencv/poses.csv" \
    "${nav_args[@]}" "${base_args[@]}" > "$o/opencv/report.json" 2> "$o/opencv/log.txt" &
  pid_ocv=$!
  rc_trn=0; rc_ocv=0
  wait "$pid_trn" || rc_trn=$?
  wait "$pid_ocv" || rc_ocv=$?
  [ "$rc_trn" -eq 0 ] || { echo "$name: trn navigate failed ($rc_trn), see $o/trn/log.txt" >&2; tail -5 "$o/trn/log.txt" >&2; exit 1; }
  [ "$rc_ocv" -eq 0 ] || { echo "$name: baseline failed ($rc_ocv), see $o/opencv/log.txt" >&2; tail -5 "$o/opencv/log.txt" >&2; exit 1; }
  "$trn" evaluate --flight "$f" --poses "$o/trn/poses.csv" --label trn --poses "$o/opencv/poses.csv" --label opencv \
    --json "$o/eval.json" > "$o/eval.txt" 2>&1
done

args=()
for i in "${!names[@]}"; do args+=("${names[$i]}" "${flights[$i]}" "${bases[$i]}"); done
"$PY" - "$OUT" "${args[@]}" <<'EOF'
import csv, json, os, sys

out, rest = sys.argv[1], sys.argv[2:]
scen = [rest[i:i + 3] for i in range(0, len(rest), 3)]
nan = float("nan")

def median(v):
    v = sorted(v)
    if not v:
        return nan
    n = len(v)
    return v[n // 2] if n % 2 else 0.5 * (v[n // 2 - 1] + v[n // 2])

def ratio(a, b):
    return a / b if b and b == b and a == a else nan

def fmt(x, spec):
    return "n/a" if x != x else format(x, spec)

rows = []
for name, flight, base in scen:
    ev = json.load(open(os.path.join(out, name, "eval.json")))
    frames = list(csv.DictReader(open(os.path.join(flight, "frames.csv"))))
    dur = float(frames[-1]["t"]) - float(frames[0]["t"]) if frames else 0.0
    r = {"scenario": name, "flight": flight, "frames": len(frames), "duration_s": dur,
         "baseline_db": base, "baseline_db_rule": json.load(open(os.path.join(out, name, "baseline-db.json")))}
    for run in ev["runs"]:
        lab = run["label"]
        fe = (run.get("fix_errors") or {}).get("pos_m") or {}
        ms = [float(x["ms"]) for x in csv.DictReader(open(run["poses"]))]
        r[lab] = {"mean": fe.get("mean", nan), "p95": fe.get("p95", nan), "max": fe.get("max", nan),
                  "fix": run["status"]["share_fix"], "ms": median(ms)}
    rows.append(r)

hdr = ["scenario", "frames (s)", "ocv tmpl",
       "trn mean m", "ocv mean m", "ratio",
       "trn p95 m", "ocv p95 m", "ratio",
       "trn fix", "ocv fix", "ratio",
       "trn worst m", "ocv worst m", "ratio",
       "trn ms", "ocv ms", "ratio"]
table = []
for r in rows:
    t, o = r["trn"], r["opencv"]
    table.append([r["scenario"], f"{r['frames']} ({r['duration_s']:.0f})", str(r["baseline_db_rule"]["template_size"]),
                  fmt(t["mean"], ".1f"), fmt(o["mean"], ".1f"), fmt(ratio(t["mean"], o["mean"]), ".2f"),
                  fmt(t["p95"], ".1f"), fmt(o["p95"], ".1f"), fmt(ratio(t["p95"], o["p95"]), ".2f"),
                  f"{100 * t['fix']:.0f}%", f"{100 * o['fix']:.0f}%", fmt(ratio(t["fix"], o["fix"]), ".2f"),
                  fmt(t["max"], ".1f"), fmt(o["max"], ".1f"), fmt(ratio(t["max"], o["max"]), ".2f"),
                  fmt(t["ms"], ".1f"), fmt(o["ms"], ".1f"), fmt(ratio(t["ms"], o["ms"]), ".2f")])

w = [max(len(h), *(len(x[i]) for x in table)) for i, h in enumerate(hdr)]
print("  ".join(h.rjust(w[i]) for i, h in enumerate(hdr)))
for x in table:
    print("  ".join(v.rjust(w[i]) for i, v in enumerate(x)))

md = ["# Navigator benchmark: trn vs OpenCV baseline", "",
      "3D position error (m) over accepted fixes (mean, p95, worst), fix share over all frames, median wall ms per "
      "processed frame (from the decoded image to the pose; both navigators at once, one core each). "
      "`ocv tmpl`: template size of the baseline's own database. Ratios are trn / opencv (error and time: lower is "
      "better; fix share: higher is better).", "",
      "| " + " | ".join(hdr) + " |", "|" + "|".join("---" if i == 0 else "---:" for i in range(len(hdr))) + "|"]
md += ["| " + " | ".join(x) + " |" for x in table]
with open(os.path.join(out, "results.md"), "w") as fh:
    fh.write("\n".join(md) + "\n")
json.dump(rows, open(os.path.join(out, "results.json"), "w"), indent=2)
print(f"\nwrote {os.path.join(out, 'results.md')}")
EOF
