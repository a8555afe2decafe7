#!/usr/bin/env bash
# Regenerates every image of the README (docs/img/*.png) with the current
# binary, so that none can go stale: the plots of one simulated flight
# (`trn evaluate --plot-dir`), one frame's match picture (`trn navigate
# --matches-dir`) and a coverage map (`trn coverage --png`), all on the
# synthetic map of scripts/sim_samples.sh (built on first use, ~5 minutes).
# Usage: scripts/docs_images.sh   (then review and commit docs/img/)
# Environment: FRAME (index of the frame whose match picture is kept; default
# the middle processed frame).
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/install-deps.sh
scripts/sim_samples.sh balloon-nadir
trn=target/release/trn
flight=target/sim-data/flights/balloon-nadir
work=target/docs-images
rm -rf "$work"
mkdir -p "$work/matches" docs/img
echo "== navigate balloon-nadir (match pictures of every processed frame)"
"$trn" navigate --db target/sim-data/map.gpkg --flight "$flight" --out "$work/poses.csv" \
  --matches-dir "$work/matches" > "$work/run.json"
"$trn" evaluate --flight "$flight" --poses "$work/poses.csv" --plot-dir "$work/plots" --band-m 2000 \
  --json "$work/eval.json" > /dev/null
for f in trajectory error_height inliers residuals; do
  cp "$work/plots/$f.png" docs/img/
done
pictures=("$work"/matches/*.png)
frame=${FRAME:-$(( ${#pictures[@]} / 2 ))}
cp "${pictures[$frame]}" docs/img/matches.png
echo "== coverage of data-samples/coverage-plan.json"
"$trn" coverage --db target/sim-data/map.gpkg --plan data-samples/coverage-plan.json \
  --png docs/img/coverage.png > "$work/coverage.json"
python3 - "$work/eval.json" "${pictures[$frame]}" <<'PY'
import json, sys
r = json.load(open(sys.argv[1]))["runs"][0]
e = r["fix_errors"]["pos_m"]
print(f"docs/img/: plots of {r['status']['share_fix'] * 100:.0f}% fixed frames, mean error {e['mean']:.1f} m; "
      f"matches.png from {sys.argv[2]}")
PY
