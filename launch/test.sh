#!/usr/bin/env bash
# The project's test command (README): sets up libtorch if needed, runs every
# test in the workspace with cargo-nextest (cargo test if nextest is not to be
# had), then builds the Python package into a cached venv and runs its pytest
# suite (the progpy cross-check included). Extra arguments go to `cargo nextest
# run` (and skip the Python suite unless BCAL_PYTEST=1), e.g. a filter:
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

rust_rc=0
if cargo nextest --version >/dev/null 2>&1; then
  cargo nextest run --workspace --no-fail-fast "$@" || rust_rc=$?
else
  cargo test --workspace --no-fail-fast "$@" || rust_rc=$?
fi

# The Python package (python/): `pip install ./python[test]` builds it with maturin (PEP 517) into a venv
# cached beside libtorch (pip's own cache: ~/.cache/pip), then its pytest suite runs against the CLI
# built above and progpy from PyPI. A filtered run (arguments given) is a Rust run: set BCAL_PYTEST=1 to
# run the Python suite too.
py_rc=0
if [[ $# -eq 0 || ${BCAL_PYTEST:-0} == 1 ]]; then
  py_started=$(date +%s)
  PYENV=${BCAL_PYENV:-${BCAL_CACHE:-$HOME/.cache/bcal}/pyenv}
  if [[ ! -x $PYENV/bin/python ]]; then
    echo "test.sh: creating the Python test environment $PYENV"
    python3 -m venv "$PYENV"
  fi
  "$PYENV/bin/python" -m pip install --quiet --disable-pip-version-check "$REPO/python[test]"
  echo "test.sh: Python package built and installed in $(( $(date +%s) - py_started )) s"
  BCAL_BIN="$REPO/target/debug/bcal" BCAL_REQUIRE_CLI=1 \
    "$PYENV/bin/python" -m pytest "$REPO/python/tests" -q -p no:cacheprovider -W ignore::DeprecationWarning \
    || py_rc=$?
  echo "test.sh: Python suite in $(( $(date +%s) - py_started )) s"
fi
(( rust_rc == 0 && py_rc == 0 )) || exit 1
