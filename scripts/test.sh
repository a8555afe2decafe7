#!/usr/bin/env bash
# The test command (README, CI): installs what is missing, fetches the real
# samples, prepares the Python reference tools, then one cargo invocation builds
# and runs every test of the workspace.
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/install-deps.sh
data-samples/fetch.sh >/dev/null
scripts/venv.sh >/dev/null
cargo test --workspace --all-targets "$@"
