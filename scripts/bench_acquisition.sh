#!/usr/bin/env bash
# Acquisition from a large initial error (issue #13): the realistic
# sierra-balloon-nadir-lost flight (run scripts/bench_realistic.sh first) with
# its initial guess moved DIST metres north-east of the true start (keeping the
# scenario's guessed height and 5-degree attitude error), navigated by trn with
# the default --init-sigma-m (300 m) and with --init-sigma-m DIST. Prints fix
# share, first fixed frame, errors and median ms; results in
# target/realistic/acquisition/results.md.
# Usage: scripts/bench_acquisition.sh [DIST_M ...]   (default: 3000 6000 10000)
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${OUT:-target/realistic}
src="$OUT/flights/sierra-balloon-nadir-lost"
db="$OUT/db/sierra.gpkg"
[ -f "$src/frames.csv" ] && [ -f "$db" ] || { echo "run scripts/bench_realistic.sh first ($src, $db)" >&2; exit 1; }
cargo build --release --quiet --bin trn
trn=target/release/trn
dists=("$@"); [ ${#dists[@]} -eq 0 ] && dists=(3000 6000 10000)
work="$OUT/acquisition"
mkdir -p "$work"
rows=()
for d in "${dists[@]}"; do
  f="$work/flight-$d"
  rm -rf "$f"; mkdir -p "$f"
  for x in "$src"/*; do ln -s "$(readlink -f "$x")" "$f/"; done
  rm "$f/init.json"
  python3 - "$src" "$f" "$d" <<'PY'
import json, math, sys
src, dst, d = sys.argv[1], sys.argv[2], float(sys.argv[3])
first = open(f"{src}/truth.csv").read().splitlines()[1].split(",")
lat, lon = float(first[1]), float(first[2])
init = json.load(open(f"{src}/init.json"))
# d metres toward the north-east on a local sphere (accurate to metres here).
r = 6371000.0
init["lat"] = lat + math.degrees(d * math.cos(math.radians(45)) / r)
init["lon"] = lon + math.degrees(d * math.sin(math.radians(45)) / (r * math.cos(math.radians(lat))))
json.dump(init, open(f"{dst}/init.json", "w"))
PY
  for sigma in 300 "$d"; do
    o="$work/$d-sigma-$sigma"; mkdir -p "$o"
    echo "== guess $d m off, --init-sigma-m $sigma" >&2
    TRN_LOG=warn "$trn" navigate --db "$db" --flight "$f" --out "$o/poses.csv" --init-sigma-m "$sigma" > "$o/report.json"
    "$trn" evaluate --flight "$f" --poses "$o/poses.csv" --json "$o/eval.json" > /dev/null
    rows+=("$d $sigma $o")
  done
done
python3 - "$work/results.md" "${rows[@]}" <<'PY'
import csv, json, sys
out, rows = sys.argv[1], sys.argv[2:]
lines = ["| guess off (m) | --init-sigma-m | fix share | first fix (frame) | mean m | worst m | rejected solutions | median ms |",
         "|---:|---:|---:|---:|---:|---:|---|---:|"]
for r in rows:
    d, sigma, o = r.split(" ", 2)
    e = json.load(open(f"{o}/eval.json"))["runs"][0]
    rep = json.load(open(f"{o}/report.json"))
    poses = list(csv.DictReader(open(f"{o}/poses.csv")))
    first = next((i for i, p in enumerate(poses) if p["status"] == "fix"), None)
    share = e["status"]["share_fix"]
    fe = e["fix_errors"]["pos_m"] if share > 0 else None
    rj = rep["rejected"]
    rej = f"{rj['few_inliers']} few inliers, {rj['inlier_share']} low share, {rj['height']} height"
    lines.append(f"| {d} | {sigma} | {share*100:.0f}% | {'-' if first is None else first} | "
                 f"{fe['mean']:.0f} | {fe['max']:.0f} | {rej} | {rep['median_ms']:.0f} |"
                 if fe else f"| {d} | {sigma} | 0% | - | - | - | {rej} | {rep['median_ms']:.0f} |")
open(out, "w").write("\n".join(lines) + "\n")
print("\n".join(lines))
PY
