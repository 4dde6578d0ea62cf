#!/usr/bin/env bash
# bcal's main job: set up libtorch if missing, build, train the calibrator on the default config within a
# time budget, evaluate it against the UKF and the direct mapping, and print the report.
#
#   launch/run.sh [--experiment single-q|single-r|multi] [--budget-s SECONDS] [--actors N] [--name NAME]
#
# Defaults: experiment multi, budget 900 s, one actor per core, run folder runs/<experiment>-<time>.
set -euo pipefail
cd "$(dirname "$0")/.."

experiment=multi
budget_s=900
actors=""
name=""
usage() { sed -n '2,7p' "$0" | sed 's/^# \{0,1\}//'; }
while [ $# -gt 0 ]; do
  case "$1" in
    --experiment) experiment="${2:?--experiment needs a value}"; shift 2 ;;
    --budget-s) budget_s="${2:?--budget-s needs a value}"; shift 2 ;;
    --actors) actors="${2:?--actors needs a value}"; shift 2 ;;
    --name) name="${2:?--name needs a value}"; shift 2 ;;
    -h|--help) usage; exit 0 ;;
    *) echo "run.sh: unknown argument '$1'" >&2; usage >&2; exit 2 ;;
  esac
done
case "$experiment" in single-q|single-r|multi) ;; *) echo "run.sh: --experiment must be single-q, single-r or multi" >&2; exit 2 ;; esac
[ -n "$name" ] || name="$experiment-$(date -u +%Y%m%d-%H%M%S)"

echo "== libtorch"
bash launch/setup-libtorch.sh
echo "== build (release)"
cargo build --release --bins --workspace
bin=target/release
echo "== data set"
"$bin/bcal" dataset generate --experiment "$experiment"
echo "== train ($experiment, budget ${budget_s} s)"
actor_args=()
[ -z "$actors" ] || actor_args=(--actors "$actors")
"$bin/bcal" train --experiment "$experiment" --budget-s "$budget_s" "${actor_args[@]}" --name "$name"
run="runs/$name"
echo "== evaluate"
"$bin/bcal" eval --run "$run" --experiment "$experiment"
echo
if [ -f "$run/report.md" ]; then
  cat "$run/report.md"
fi
echo
echo "report: $run/report.md (and report.json, plots/)"
