#!/usr/bin/env bash
# Navigator benchmark: trn navigate against the OpenCV baseline
# (scripts/baseline_opencv.py) on the same flights, in the same run, each pinned
# to one core, both scored by trn evaluate against the flight's truth.csv.
#
# Usage: scripts/bench_nav.sh [FLIGHT_DIR ...]
#   default: every flight folder in target/sim-data/flights/ (scripts/sim_samples.sh)
# Environment:
#   DB=target/sim-data/map.gpkg   landmark database
#   OUT=target/bench-nav          results: OUT/<flight>/{trn,opencv}/poses.csv (+ matches.csv),
#                                 OUT/<flight>/eval.{json,txt}, OUT/results.md
#   CORE=0                        CPU core both navigators are pinned to (taskset)
#   PY=.venv/bin/python           Python with numpy + opencv-python-headless
#   NAV_ARGS=, BASELINE_ARGS=     extra options for both, e.g. "--rate 2" or "--no-gyro"
#                                 (NAV_ARGS go to both, BASELINE_ARGS to the baseline only,
#                                 e.g. "--ncc interior")
# Prints, per flight: mean / p95 3D position error over fix frames, fix share
# over all frames and median ms per frame, for both, and the ratios
# trn / opencv (error and time; the target is <= 0.5) and fix share trn / opencv.
set -euo pipefail
cd "$(dirname "$0")/.."
DB=${DB:-target/sim-data/map.gpkg}
OUT=${OUT:-target/bench-nav}
CORE=${CORE:-0}
PY=${PY:-.venv/bin/python}
read -r -a nav_args <<< "${NAV_ARGS:-}"
read -r -a base_args <<< "${BASELINE_ARGS:-}"

flights=("$@")
if [ ${#flights[@]} -eq 0 ]; then
  for d in target/sim-data/flights/*/; do
    [ -f "$d/frames.csv" ] && flights+=("${d%/}")
  done
fi
[ ${#flights[@]} -gt 0 ] || { echo "no flights (run scripts/sim_samples.sh first)" >&2; exit 1; }
[ -f "$DB" ] || { echo "$DB: no landmark database (run scripts/sim_samples.sh first)" >&2; exit 1; }
[ -x "$PY" ] || { echo "$PY: no Python (run scripts/venv.sh)" >&2; exit 1; }
"$PY" -c "import cv2, numpy" || { echo "$PY lacks opencv-python-headless / numpy" >&2; exit 1; }

cargo build --release --quiet --bin trn
trn=target/release/trn
pin=()
if command -v taskset >/dev/null; then pin=(taskset -c "$CORE"); fi
mkdir -p "$OUT"

for f in "${flights[@]}"; do
  name=$(basename "$f")
  o="$OUT/$name"
  rm -rf "$o"; mkdir -p "$o/trn" "$o/opencv"
  echo "== $name: trn navigate" >&2
  "${pin[@]}" "$trn" navigate --db "$DB" --flight "$f" --out "$o/trn/poses.csv" \
    "${nav_args[@]}" > "$o/trn/report.json"
  echo "== $name: OpenCV baseline" >&2
  "${pin[@]}" "$PY" scripts/baseline_opencv.py --db "$DB" --flight "$f" --out "$o/opencv/poses.csv" \
    "${nav_args[@]}" "${base_args[@]}" > "$o/opencv/report.json"
  "$trn" evaluate --flight "$f" --poses "$o/trn/poses.csv" --label trn --poses "$o/opencv/poses.csv" --label opencv \
    --json "$o/eval.json" > "$o/eval.txt" 2>&1
done

"$PY" - "$OUT" "${flights[@]}" <<'EOF'
import csv, json, os, sys

out, flights = sys.argv[1], sys.argv[2:]

def median(v):
    v = sorted(v)
    if not v:
        return float("nan")
    n = len(v)
    return v[n // 2] if n % 2 else 0.5 * (v[n // 2 - 1] + v[n // 2])

def ratio(a, b):
    return a / b if b and b == b and a == a else float("nan")

def fmt(x, spec):
    return "n/a" if x != x else format(x, spec)

rows = []
for f in flights:
    name = os.path.basename(f.rstrip("/"))
    ev = json.load(open(os.path.join(out, name, "eval.json")))
    frames = list(csv.DictReader(open(os.path.join(f, "frames.csv"))))
    dur = float(frames[-1]["t"]) - float(frames[0]["t"]) if frames else 0.0
    r = {"flight": name, "frames": len(frames), "duration_s": dur}
    for run in ev["runs"]:
        lab = run["label"]
        fe = (run.get("fix_errors") or {}).get("pos_m") or {"mean": float("nan"), "p95": float("nan")}
        ms = [float(x["ms"]) for x in csv.DictReader(open(run["poses"]))]
        r[lab] = {"mean": fe["mean"], "p95": fe["p95"], "fix": run["status"]["share_fix"], "ms": median(ms)}
    rows.append(r)

hdr = ["flight", "frames (s)",
       "trn mean m", "ocv mean m", "ratio",
       "trn p95 m", "ocv p95 m", "ratio",
       "trn fix", "ocv fix", "ratio",
       "trn ms", "ocv ms", "ratio"]
table = []
for r in rows:
    t, o = r["trn"], r["opencv"]
    table.append([r["flight"], f"{r['frames']} ({r['duration_s']:.0f})",
                  fmt(t["mean"], ".1f"), fmt(o["mean"], ".1f"), fmt(ratio(t["mean"], o["mean"]), ".2f"),
                  fmt(t["p95"], ".1f"), fmt(o["p95"], ".1f"), fmt(ratio(t["p95"], o["p95"]), ".2f"),
                  f"{100 * t['fix']:.0f}%", f"{100 * o['fix']:.0f}%", fmt(ratio(t["fix"], o["fix"]), ".2f"),
                  f"{t['ms']:.1f}", f"{o['ms']:.1f}", fmt(ratio(t["ms"], o["ms"]), ".2f")])

w = [max(len(h), *(len(x[i]) for x in table)) for i, h in enumerate(hdr)]
print("  ".join(h.rjust(w[i]) for i, h in enumerate(hdr)))
for x in table:
    print("  ".join(v.rjust(w[i]) for i, v in enumerate(x)))

md = ["# Navigator benchmark: trn vs OpenCV baseline", "",
      "3D position error (m) over fix frames, fix share over all frames, median wall ms per processed frame "
      "(from the decoded image to the pose, one core each). Ratios are trn / opencv (error and time: lower is better, "
      "target <= 0.5; fix share: higher is better).", "",
      "| " + " | ".join(hdr) + " |", "|" + "|".join("---" if i == 0 else "---:" for i in range(len(hdr))) + "|"]
md += ["| " + " | ".join(x) + " |" for x in table]
with open(os.path.join(out, "results.md"), "w") as fh:
    fh.write("\n".join(md) + "\n")
json.dump(rows, open(os.path.join(out, "results.json"), "w"), indent=2)
print(f"\nwrote {os.path.join(out, 'results.md')}")
EOF
