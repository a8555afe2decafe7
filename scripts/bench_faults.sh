#!/usr/bin/env bash
# Sensor faults (issue #13: doubt it, report it, recover): a realistic flight
# (run scripts/bench_realistic.sh first; default sierra-balloon-nadir, 30 km)
# with its IMU changed, navigated by trn on the default database: a gyro
# glitch (four samples over 20 ms turned about the IMU's x axis, DEG in all),
# an accelerometer shock (its x axis off by M m/s^2 for SECONDS), a gap (no
# sample for SECONDS), a spike (a value no sensor measures, VALUE, in the
# gyro's x of the first sample after T0 and the accelerometer's x of the
# next), or a log that ends at T (end:T) or starts there (start:T). Prints, per case, the fixes, the mean and worst error of the fixes,
# the error at the last frame, the farthest fix in its own sigmas, and what
# the run report says: gyro and accelerometer jumps doubted, fixes found
# with the gyro's jumps undone (a glitch, not a turn), map offsets
# restarted, frames doubted after a run of misses, IMU gaps, IMU samples
# left out as beyond the sensors' range, the frames' time the log does not
# cover (s); results in OUT/faults/results.md.
# A run whose poses trn evaluate cannot read (not finite) is a row that
# says so.
# Usage: scripts/bench_faults.sh [CASE ...]   (CASE: none, glitch:DEG@T0,
#   shock:MxSECONDS@T0, gap:SECONDS@T0, spike:VALUE@T0, end:T or start:T;
#   default: none
#   glitch:1@10 glitch:5@10 glitch:10@10 glitch:30@10 shock:500x0.02@10
#   shock:30x1@10 shock:100x1@10 shock:20x5@10 gap:1@10 gap:3@10 gap:10@10
#   gap:3@30 spike:1e300@10 end:20 start:5)
# Environment: OUT=target/realistic; FLIGHT=another realistic flight's name;
#   TRN=path of a trn binary (default: this checkout's, built); NAV_ARGS more
#   trn navigate options.
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${OUT:-target/realistic}
name=${FLIGHT:-sierra-balloon-nadir}
src="$OUT/flights/$name"
world=${name%%-*}
db="$OUT/db/$world.gpkg"
[ -f "$src/frames.csv" ] && [ -f "$db" ] || { echo "run scripts/bench_realistic.sh first ($src, $db)" >&2; exit 1; }
if [ -z "${TRN:-}" ]; then cargo build --release --quiet --bin trn; fi
trn=${TRN:-target/release/trn}
read -r -a nav_args <<< "${NAV_ARGS:-}"
cases=("$@")
[ ${#cases[@]} -gt 0 ] || cases=(none glitch:1@10 glitch:5@10 glitch:10@10 glitch:30@10 shock:500x0.02@10 shock:30x1@10
  shock:100x1@10 shock:20x5@10 gap:1@10 gap:3@10 gap:10@10 gap:3@30 spike:1e300@10 end:20 start:5)
work="$OUT/faults"
rm -rf "$work"; mkdir -p "$work"
rows=()
for c in "${cases[@]}"; do
  d="$work/${c//[:@]/-}"; f="$d/flight"
  mkdir -p "$f"
  # The flight's files, its images linked; imu.csv rewritten for the case.
  for x in "$src"/*; do
    case "$(basename "$x")" in imu.csv) ;; *) ln -s "$(readlink -f "$x")" "$f/";; esac
  done
  python3 - "$src/imu.csv" "$f/imu.csv" "$c" <<'PY'
import csv, math, sys
src, dst, case = sys.argv[1:4]
rows = list(csv.reader(open(src)))
head, body = rows[0], rows[1:]
if case.startswith(("end:", "start:")):
    kind, t = case.split(":")
    t = float(t)
    body = [r for r in body if (float(r[0]) <= t if kind == "end" else float(r[0]) >= t)]
elif case != "none":
    kind, rest = case.split(":")
    size, t0 = rest.split("@")
    t0 = float(t0)
    if kind == "shock":
        force, seconds = (float(x) for x in size.split("x"))
        for r in body:
            if t0 < float(r[0]) <= t0 + seconds + 1e-9:
                r[4] = repr(float(r[4]) + force)
    size = float(size) if kind != "shock" else 0.0
    if kind == "glitch":
        rate = math.radians(size) / 0.02
        for r in body:
            if t0 < float(r[0]) <= t0 + 0.02 + 1e-9:
                r[1] = repr(float(r[1]) + rate)
    elif kind == "spike":
        # A value no sensor measures (a flipped bit in an exponent): the
        # gyro's x of the first sample after T0, the accelerometer's x of
        # the next.
        after = [r for r in body if float(r[0]) > t0]
        after[0][1] = repr(size)
        after[1][4] = repr(size)
    elif kind == "gap":
        body = [r for r in body if not (t0 <= float(r[0]) < t0 + size)]
    elif kind != "shock":
        sys.exit(f"unknown case {case!r}: none, glitch:DEG@T0, shock:MxSECONDS@T0, gap:SECONDS@T0, spike:VALUE@T0, end:T or start:T")
csv.writer(open(dst, "w"), lineterminator="\n").writerows([head] + body)
PY
  "$trn" navigate --db "$db" --flight "$f" --out "$d/poses.csv" "${nav_args[@]}" > "$d/report.json" 2> "$d/log.txt"
  if ! "$trn" evaluate --flight "$f" --poses "$d/poses.csv" --json "$d/eval.json" > "$d/eval.txt" 2>&1; then
    rows+=("| $c | $(grep -m1 '^error' "$d/eval.txt" | cut -c1-120) | | | | | | | | | | | |")
    continue
  fi
  rows+=("$(python3 - "$d/eval.json" "$d/report.json" "$c" <<'PY'
import json, sys
e = json.load(open(sys.argv[1]))['runs'][0]
report = json.load(open(sys.argv[2]))
out = (report.get('imu_out_of_range') or {}).get('samples', 0) if 'imu_out_of_range' in report else 'n/a'
uncovered = f"{sum(u['to_t'] - u['from_t'] for u in report['imu_uncovered']):.1f}" if 'imu_uncovered' in report else 'n/a'
fr = e['per_frame']
fixes = [r['error']['pos_m'] for r in fr if r['status'] == 'fix']
mean = sum(fixes) / len(fixes) if fixes else float('nan')
worst = max(fixes) if fixes else float('nan')
gaps = len(report.get('imu_gaps', []))
farthest = e.get('consistency', {}).get('max_sigma_distance')
farthest = f"{farthest:.1f}" if farthest is not None else "n/a"
print(f"| {sys.argv[3]} | {len(fixes)} of {len(fr)} | {mean:.1f} | {worst:.1f} | {fr[-1]['error']['pos_m']:.1f} | {farthest} | {report.get('gyro_jumps', 'n/a')} | {report.get('gyro_jumps_undone', 'n/a')} | {report.get('accel_jumps', 'n/a')} | {report.get('map_doubts', 'n/a')} | {report.get('doubted_frames', 'n/a')} | {gaps} | {out} | {uncovered} |")
PY
)")
done
{
  echo "Sensor faults: $name, default database"
  echo
  echo "| case | fixes | mean m | worst m | last frame's error m | farthest fix (sigma) | gyro jumps doubted | fixes with them undone | accelerometer jumps doubted | map offsets restarted | frames doubted | IMU gaps reported | IMU samples left out | frames' time without IMU (s) |"
  echo "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"
  printf '%s\n' "${rows[@]}"
} | tee "$work/results.md"
