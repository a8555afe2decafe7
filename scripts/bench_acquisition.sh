#!/usr/bin/env bash
# Acquisition from a large initial error (issue #13): the realistic
# sierra-balloon-nadir-lost flight (run scripts/bench_realistic.sh first) with
# its initial guess moved DIST metres north-east of the true start (keeping the
# scenario's guessed height and 5-degree attitude error, or with DIST:DEG,
# the guess's attitude also pitched by DEG more, and with DIST:DEG:YAW also
# turned by YAW about the local vertical: its heading off), navigated by trn with the
# default --init-sigma-m (300 m) and --init-sigma-deg (2), and told the error
# (--init-sigma-m DIST, and --init-sigma-deg of the guess's attitude error
# when DEG or YAW is given). Prints fix share, first fixed frame, errors and median
# ms; results in target/realistic/acquisition/results.md.
# Usage: scripts/bench_acquisition.sh [DIST_M[:DEG[:YAW]] ...]   (the guess
#   moved DIST_M toward AZ, below)
#   (default: 3000 6000 10000 10000:10 3000:0:15 10000:0:30)
# Environment: OUT=target/realistic; TRN=path of a trn binary (default: built);
#   FLIGHT=another realistic flight's name (e.g. sierra-low-pass; its results in
#   OUT/acquisition-FLIGHT/results.md); AZ=the direction the guess is moved
#   toward (deg from north, default 45: north-east)
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${OUT:-target/realistic}
name=${FLIGHT:-sierra-balloon-nadir-lost}
src="$OUT/flights/$name"
db="$OUT/db/${name%%-*}.gpkg"
[ -f "$src/frames.csv" ] && [ -f "$db" ] || { echo "run scripts/bench_realistic.sh first ($src, $db)" >&2; exit 1; }
if [ -z "${TRN:-}" ]; then cargo build --release --quiet --bin trn; fi
trn=${TRN:-target/release/trn}
cases=("$@"); [ ${#cases[@]} -eq 0 ] && cases=(3000 6000 10000 10000:10 3000:0:15 10000:0:30)
work="$OUT/acquisition${FLIGHT:+-$FLIGHT}${AZ:+-az$AZ}"
mkdir -p "$work"
rows=()
for c in "${cases[@]}"; do
  IFS=: read -r d deg yaw <<< "$c"; deg=${deg:-0}; yaw=${yaw:-0}
  for v in "$d" "$deg" "$yaw"; do
    python3 -c "import sys; float(sys.argv[1])" "$v" 2>/dev/null \
      || { echo "case '$c': '$v' is not a number (DIST_M[:DEG[:YAW]])" >&2; exit 1; }
  done
  tag="$d"; [ "$deg" != 0 ] && tag="$tag-$deg"; [ "$yaw" != 0 ] && tag="$tag-yaw$yaw"
  f="$work/flight-$tag"
  rm -rf "$f"; mkdir -p "$f"
  for x in "$src"/*; do ln -s "$(readlink -f "$x")" "$f/"; done
  rm "$f/init.json"
  # The guess's attitude error (deg) against the first true attitude.
  att=$(python3 - "$src" "$f" "$d" "$deg" "${AZ:-45}" "$yaw" <<'PY'
import json, math, sys
src, dst, d, deg, az, yaw = sys.argv[1], sys.argv[2], float(sys.argv[3]), float(sys.argv[4]), float(sys.argv[5]), float(sys.argv[6])
first = open(f"{src}/truth.csv").read().splitlines()[1].split(",")
lat, lon = float(first[1]), float(first[2])
q_true = [float(x) for x in first[4:8]]
init = json.load(open(f"{src}/init.json"))
# d metres toward azimuth az on a local sphere (accurate to metres here).
r = 6371000.0
init["lat"] = lat + math.degrees(d * math.cos(math.radians(az)) / r)
init["lon"] = lon + math.degrees(d * math.sin(math.radians(az)) / (r * math.cos(math.radians(lat))))
def mul(a, b):
    w1, x1, y1, z1 = a; w2, x2, y2, z2 = b
    return [w1*w2 - x1*x2 - y1*y2 - z1*z2, w1*x2 + x1*w2 + y1*z2 - z1*y2,
            w1*y2 - x1*z2 + y1*w2 + z1*x2, w1*z2 + x1*y2 - y1*x2 + z1*w2]
q = init["q_ecef_cam"]
# Pitch the camera by deg more (about its own x axis).
h = math.radians(deg) / 2
q = mul(q, [math.cos(h), math.sin(h), 0.0, 0.0])
# Turn it by yaw about the local vertical at the guess (in ECEF).
la, lo = math.radians(init["lat"]), math.radians(init["lon"])
up = [math.cos(la) * math.cos(lo), math.cos(la) * math.sin(lo), math.sin(la)]
h = math.radians(yaw) / 2
q = mul([math.cos(h)] + [math.sin(h) * u for u in up], q)
init["q_ecef_cam"] = q
json.dump(init, open(f"{dst}/init.json", "w"))
dot = abs(sum(a * b for a, b in zip(q, q_true)))
print(f"{math.degrees(2 * math.acos(min(1.0, dot))):.1f}")
PY
)
  for told in no yes; do
    sigma=300; sdeg=2
    if [ $told = yes ]; then sigma=$d; { [ "$deg" != 0 ] || [ "$yaw" != 0 ]; } && sdeg=$att; fi
    o="$work/$tag-sigma-$sigma-$sdeg"; mkdir -p "$o"
    echo "== guess $d m and $att deg off, --init-sigma-m $sigma --init-sigma-deg $sdeg" >&2
    TRN_LOG=warn "$trn" navigate --db "$db" --flight "$f" --out "$o/poses.csv" \
      --init-sigma-m "$sigma" --init-sigma-deg "$sdeg" > "$o/report.json"
    "$trn" evaluate --flight "$f" --poses "$o/poses.csv" --json "$o/eval.json" > /dev/null
    rows+=("$d $yaw $att $sigma $sdeg $o")
  done
done
python3 - "$work/results.md" "${rows[@]}" <<'PY'
import csv, json, sys
out, rows = sys.argv[1], sys.argv[2:]
lines = ["| guess off (m) | heading turned (deg) | attitude off (deg) | --init-sigma-m | --init-sigma-deg | fix share | first fix (frame) | mean m | worst m | rejected solutions | first frame ms | median ms |",
         "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|---:|---:|"]
for r in rows:
    d, yaw, att, sigma, sdeg, o = r.split(" ", 5)
    e = json.load(open(f"{o}/eval.json"))["runs"][0]
    rep = json.load(open(f"{o}/report.json"))
    poses = list(csv.DictReader(open(f"{o}/poses.csv")))
    first = next((i for i, p in enumerate(poses) if p["status"] == "fix"), None)
    share = e["status"]["share_fix"]
    fe = e["fix_errors"]["pos_m"] if share > 0 else None
    rj = rep["rejected"]
    rej = f"{rj['few_inliers']} few inliers, {rj['inlier_share']} low share, {rj['height']} height, {rj.get('unconfirmed', 0) + rj.get('narrow_held', 0)} held"
    ms0 = float(poses[0]["ms"]) if poses else float("nan")
    head = f"| {d} | {yaw} | {att} | {sigma} | {sdeg} |"
    lines.append(f"{head} {share*100:.0f}% | {'-' if first is None else first} | "
                 f"{fe['mean']:.0f} | {fe['max']:.0f} | {rej} | {ms0:.0f} | {rep['median_ms']:.0f} |"
                 if fe else f"{head} 0% | - | - | - | {rej} | {ms0:.0f} | {rep['median_ms']:.0f} |")
open(out, "w").write("\n".join(lines) + "\n")
print("\n".join(lines))
PY
