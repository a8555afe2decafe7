# Sourced, from the repository root with OUT set, by the benchmarks that run
# on scripts/bench_realistic.sh's flights and databases: builds trn (a no-op
# when it is fresh, so a benchmark never runs a stale or experimental binary
# left in target/release) and finds the suite, `trn` and `suite` then naming them.
# shellcheck shell=bash disable=SC2034
trn=target/release/trn
cargo build --release --quiet --bin trn
suite="$OUT/suite.tsv"
[ -f "$suite" ] || { echo "no $suite: run scripts/bench_realistic.sh first" >&2; exit 1; }
