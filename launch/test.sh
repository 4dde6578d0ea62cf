#!/usr/bin/env bash
# The project's test command (README): sets up libtorch if needed, then runs
# every test in the workspace with cargo-nextest (cargo test if nextest is not
# to be had). Extra arguments go to `cargo nextest run`, e.g. a filter:
#   bash launch/test.sh -p bcal-learner
#   bash launch/test.sh libtorch_smoke
set -euo pipefail

REPO=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
cd "$REPO"
started=$(date +%s)
trap 'echo "test.sh: total $(( $(date +%s) - started )) s"' EXIT

# libtorch for tch (instant and silent when already assembled).
bash "$REPO/launch/setup-libtorch.sh" --quiet

if ! cargo nextest --version >/dev/null 2>&1; then
  echo "test.sh: cargo-nextest not found; installing it (cargo install cargo-nextest --locked)" >&2
  cargo install cargo-nextest --locked \
    || echo "test.sh: could not install cargo-nextest; falling back to cargo test" >&2
fi

# The binaries the process tests start, built here by the same command tests/src/lib.rs `bin()` runs
# (one feature set for the four packages), so no test waits on a build.
cargo build --bins -p bcal -p bcal-replay -p bcal-actor -p bcal-learner

if cargo nextest --version >/dev/null 2>&1; then
  cargo nextest run --workspace --no-fail-fast "$@"
else
  cargo test --workspace --no-fail-fast "$@"
fi
