#!/usr/bin/env bash
# bcal's main job: set up libtorch if missing, build, train the calibrator within a time budget, evaluate it
# against its baselines, and print the report.
#
#   launch/run.sh [--preset measured|paper-tuned|paper] [--budget-s SECONDS] [--seeds N] [--actors N]
#                 [--name NAME] [--experiment single-q|single-r|multi]
#
# Defaults: preset measured (calibration from what a battery management system measures: voltage, current and
# temperature through a sensor, any starting charge, changing loads), budget 900 s, one seed, one actor per
# core, run folder runs/<preset>-<time>. The paper's full-state setting is one flag away: --preset paper-tuned
# (hyperparameters tuned on its validation split) or --preset paper (the paper's own), with --experiment.
# With --seeds N (N >= 2) it trains and evaluates seeds 1..N into runs/<name>-s<k> and prints their summary
# (mean, spread and every run's value) from runs/<name>-summary/.
set -euo pipefail
cd "$(dirname "$0")/.."

experiment=multi
preset=measured
budget_s=900
seeds=1
actors=""
name=""
usage() { sed -n '2,14p' "$0" | sed 's/^# \{0,1\}//'; }
while [ $# -gt 0 ]; do
  case "$1" in
    --experiment) experiment="${2:?--experiment needs a value}"; shift 2 ;;
    --preset) preset="${2:?--preset needs a value}"; shift 2 ;;
    --budget-s) budget_s="${2:?--budget-s needs a value}"; shift 2 ;;
    --seeds) seeds="${2:?--seeds needs a value}"; shift 2 ;;
    --actors) actors="${2:?--actors needs a value}"; shift 2 ;;
    --name) name="${2:?--name needs a value}"; shift 2 ;;
    -h|--help) usage; exit 0 ;;
    *) echo "run.sh: unknown argument '$1'" >&2; usage >&2; exit 2 ;;
  esac
done
case "$experiment" in single-q|single-r|multi) ;; *) echo "run.sh: --experiment must be single-q, single-r or multi" >&2; exit 2 ;; esac
case "$preset" in measured|paper-tuned|paper) ;; *) echo "run.sh: --preset must be measured, paper-tuned or paper" >&2; exit 2 ;; esac
if [ "$preset" = measured ] && [ "$experiment" != multi ]; then
  echo "run.sh: the measured setting calibrates qMobile and Ro together (--experiment multi)" >&2; exit 2
fi
case "$seeds" in ''|*[!0-9]*|0) echo "run.sh: --seeds must be a whole number >= 1" >&2; exit 2 ;; esac
[ -n "$name" ] || name="$preset-$(date -u +%Y%m%d-%H%M%S)"

echo "== libtorch"
bash launch/setup-libtorch.sh
echo "== build (release)"
cargo build --release --bins --workspace
bin=target/release
if [ "$preset" != measured ]; then
  echo "== data set"
  "$bin/bcal" dataset generate --experiment "$experiment"
fi
actor_args=()
[ -z "$actors" ] || actor_args=(--actors "$actors")

runs=()
for seed in $(seq 1 "$seeds"); do
  run_name="$name"
  [ "$seeds" = 1 ] || run_name="$name-s$seed"
  echo "== train (preset $preset, experiment $experiment, seed $seed, budget ${budget_s} s)"
  "$bin/bcal" train --experiment "$experiment" --preset "$preset" --seed "$seed" --budget-s "$budget_s" \
    "${actor_args[@]}" --name "$run_name"
  echo "== evaluate (seed $seed)"
  "$bin/bcal" eval --run "runs/$run_name"
  runs+=("runs/$run_name")
done
echo
if [ "$seeds" = 1 ]; then
  run="${runs[0]}"
  if [ -f "$run/report.md" ]; then
    cat "$run/report.md"
  fi
  echo
  echo "report: $run/report.md (and report.json, plots)"
else
  "$bin/bcal" summarize "${runs[@]}" --out "runs/$name-summary"
  echo "reports: ${runs[*]/%//report.md}; summary: runs/$name-summary/summary.md"
fi
