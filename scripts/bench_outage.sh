#!/usr/bin/env bash
# A total cloud cover (issue #13): a realistic flight (run
# scripts/bench_realistic.sh first; default sierra-balloon-nadir, 30 km) with
# every image from T0 for DURATION seconds replaced by a uniform grey one (no
# landmark can match), navigated by trn with each --filter. Prints, per
# filter, the position error at the last frame before the outage, the drift
# at its last frame, the time from its end to the next fix and the mean error
# of the fixes after it; results in target/realistic/outage/results.md.
# (Drift: the change of the east/north/up error vector over the outage.)
# Usage: scripts/bench_outage.sh [FLIGHT [T0 [DURATION]]]   (default: sierra-balloon-nadir 15 30)
# Environment: WINDOW=F (0 < F < 1) keeps a centred box of F times the image's
# sides visible (a hole in the cloud: a few landmarks) instead of greying all;
# FILTERS="tight loose fixes" the --filter runs; TRN a trn binary to use (default:
# this checkout's, built); NAV_ARGS more trn navigate options; WORK the
# work folder (default OUT/outage).
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${OUT:-target/realistic}
name=${1:-sierra-balloon-nadir}; t0=${2:-15}; dur=${3:-30}
src="$OUT/flights/$name"
world=${name%%-*}
db="$OUT/db/$world.gpkg"
[ -f "$src/frames.csv" ] && [ -f "$db" ] || { echo "run scripts/bench_realistic.sh first ($src, $db)" >&2; exit 1; }
if [ -z "${TRN:-}" ]; then cargo build --release --quiet --bin trn; fi
trn=${TRN:-target/release/trn}
read -r -a nav_args <<< "${NAV_ARGS:-}"
work=${WORK:-$OUT/outage}
f="$work/flight"
rm -rf "$work"; mkdir -p "$f/images"
for x in "$src"/*; do [ "$(basename "$x")" = images ] || ln -s "$(readlink -f "$x")" "$f/"; done
for x in "$src"/images/*; do ln -s "$(readlink -f "$x")" "$f/images/"; done
# Grey out the outage's images (a uniform picture: no texture, no match).
"${PY:-.venv/bin/python}" - "$src" "$f" "$t0" "$dur" "${WINDOW:-0}" <<'PY'
import csv, os, sys
import cv2
src, dst, t0, dur, window = sys.argv[1], sys.argv[2], float(sys.argv[3]), float(sys.argv[4]), float(sys.argv[5])
n = 0
for row in csv.DictReader(open(f"{src}/frames.csv")):
    t = float(row['t'])
    if t0 <= t < t0 + dur:
        img = cv2.imread(f"{src}/{row['image']}", cv2.IMREAD_UNCHANGED)
        out = img.copy()
        out[...] = 128
        if window > 0:
            h, w = img.shape[:2]
            y0, x0 = int(h * (1 - window) / 2), int(w * (1 - window) / 2)
            out[y0:h - y0, x0:w - x0] = img[y0:h - y0, x0:w - x0]
        os.remove(f"{dst}/{row['image']}")
        cv2.imwrite(f"{dst}/{row['image']}", out)
        n += 1
print(f"{n} images from t = {t0} s for {dur} s: {'a centred box of %g of the sides kept' % window if window > 0 else 'grey'}", file=sys.stderr)
PY
rows=()
for filter in ${FILTERS:-tight loose fixes}; do
  d="$work/$filter"; mkdir -p "$d"
  "$trn" navigate --db "$db" --flight "$f" --filter "$filter" --out "$d/poses.csv" "${nav_args[@]}" > "$d/report.json" 2> "$d/log.txt"
  "$trn" evaluate --flight "$f" --poses "$d/poses.csv" --json "$d/eval.json" > /dev/null 2>&1
  rows+=("$(python3 - "$d/eval.json" "$t0" "$dur" "$filter" <<'PY'
import json, sys
e = json.load(open(sys.argv[1]))['runs'][0]
t0, dur, filt = float(sys.argv[2]), float(sys.argv[3]), sys.argv[4]
fr = e['per_frame']
def err(r): return r['error']['pos_m']
before = [r for r in fr if r['t'] < t0]
during = [r for r in fr if t0 <= r['t'] < t0 + dur]
after = [r for r in fr if r['t'] >= t0 + dur]
first_fix = next((r['t'] - (t0 + dur) for r in after if r['status'] == 'fix'), float('nan'))
fixes_after = [err(r) for r in after if r['status'] == 'fix']
mean_after = sum(fixes_after) / len(fixes_after) if fixes_after else float('nan')
# Drift: how far the estimate moved against the truth over the outage (the
# change of the east/north/up error vector, not of its length).
e0, e1 = before[-1]['error']['enu_m'], during[-1]['error']['enu_m']
drift = sum((a - b) ** 2 for a, b in zip(e0, e1)) ** 0.5
used = sum(1 for r in during if (r.get('inliers') or 0) > 0)
fixes_during = [err(r) for r in during if r['status'] == 'fix']
worst = f"{max(fixes_during):.1f}" if fixes_during else "none"
print(f"| {filt} | {err(before[-1]):.1f} | {err(during[-1]):.1f} | {drift:.1f} | {first_fix:.1f} | {mean_after:.1f} | {used} | {len(fixes_during)} | {worst} |")
PY
)")
done
{
  echo "Outage: $name, images from t = $t0 s greyed for $dur s (WINDOW=${WINDOW:-0})"
  echo
  echo "| filter | error before (m) | error at the outage's end (m) | drift (m) | next fix after (s) | mean error after (m) | frames with inliers in the outage | fixes in the outage | worst of them (m) |"
  echo "|---|---:|---:|---:|---:|---:|---:|---:|---:|"
  printf '%s\n' "${rows[@]}"
} | tee "$work/results.md"
