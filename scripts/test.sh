#!/usr/bin/env bash
# The test command (README, CI): installs what is missing, fetches the real
# samples, prepares the Python reference tools, then one cargo invocation builds
# and runs every test of the workspace. Ends with one summary line
# "N passed, M failed" over all test binaries.
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/install-deps.sh
data-samples/fetch.sh >/dev/null
scripts/venv.sh >/dev/null
log=$(mktemp)
trap 'rm -f "$log"' EXIT
status=0
# A one-off build gains nothing from incremental caches (1.3 GB on disk).
export CARGO_INCREMENTAL="${CARGO_INCREMENTAL:-0}"
cargo test --workspace "$@" 2>&1 | tee "$log" || status=$?
passed=$(grep -Eo '^test result: .* ([0-9]+) passed' "$log" | grep -Eo '[0-9]+ passed' | awk '{s+=$1} END {print s+0}')
failed=$(grep -Eo '^test result: .* ([0-9]+) failed' "$log" | grep -Eo '[0-9]+ failed' | awk '{s+=$1} END {print s+0}')
echo
echo "$passed passed, $failed failed"
exit "$status"
