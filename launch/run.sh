#!/usr/bin/env bash
# bcal's main job: set up libtorch if missing, build, train the calibrator within a time budget, evaluate it
# against its baselines, and print the report.
#
#   launch/run.sh [--preset measured|paper-tuned|paper] [--budget-s SECONDS] [--seeds N] [--actors N]
#                 [--name NAME] [--experiment single-q|single-r|multi]
#   launch/run.sh --cell ID [--data PATH] [--train-cycles A..B] [--cutoff-v V] [--budget-s SECONDS] [--name NAME]
#
# Defaults: preset measured (calibration from what a battery management system measures: voltage, current and
# temperature through a sensor, any starting charge, changing loads), budget 900 s, one seed, one actor per
# core, run folder runs/<preset>-<time>. The paper's full-state setting is one flag away: --preset paper-tuned
# (hyperparameters tuned for minutes of training, docs/tuning.md) or --preset paper (the paper's own), with
# --experiment.
# With --seeds N (N >= 2) it trains and evaluates seeds 1..N into runs/<name>-s<k> and prints their summary
# (mean, spread and every run's value) from runs/<name>-summary/.
# With --cell ID: a real cell (default data ../shared/data/nasa-pcoe, training cycles the first third of the
# cell's discharges, at most 40, as bcal calibrate takes them): the doctor
# diagnoses the training cycles alone (fits their first three quarters, judges the last), a measured-only
# policy is trained on the cell's own setting and the diagnosed model (bcal cell-config --model), and bcal
# calibrate runs it, the joint UKF and the references on the later cycles and scores them against the
# cycler (runs/<name>/calibration/calibration.md).
set -euo pipefail
cd "$(dirname "$0")/.."

experiment=multi
preset=measured
budget_s=900
seeds=1
actors=""
name=""
cell=""
data="../shared/data/nasa-pcoe"
train_cycles=""
cutoff_args=()
usage() { sed -n '2,20p' "$0" | sed 's/^# \{0,1\}//'; }
while [ $# -gt 0 ]; do
  case "$1" in
    --experiment) experiment="${2:?--experiment needs a value}"; shift 2 ;;
    --preset) preset="${2:?--preset needs a value}"; shift 2 ;;
    --budget-s) budget_s="${2:?--budget-s needs a value}"; shift 2 ;;
    --seeds) seeds="${2:?--seeds needs a value}"; shift 2 ;;
    --actors) actors="${2:?--actors needs a value}"; shift 2 ;;
    --name) name="${2:?--name needs a value}"; shift 2 ;;
    --cell) cell="${2:?--cell needs a value}"; shift 2 ;;
    --data) data="${2:?--data needs a value}"; shift 2 ;;
    --train-cycles) train_cycles="${2:?--train-cycles needs a value}"; shift 2 ;;
    --cutoff-v) cutoff_args=(--cutoff-v "${2:?--cutoff-v needs a value}"); shift 2 ;;
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
if [ -n "$cell" ]; then
  [ -e "$data" ] || { echo "run.sh: no data at $data (pass --data PATH: a NASA PCoE folder or a CSV)" >&2; exit 2; }
  [ -n "$name" ] || name="cell-$cell-$(date -u +%Y%m%d-%H%M%S)"
else
  [ -n "$name" ] || name="$preset-$(date -u +%Y%m%d-%H%M%S)"
fi

echo "== libtorch"
bash launch/setup-libtorch.sh
echo "== build (release)"
cargo build --release --bins --workspace
bin=target/release
actor_args=()
[ -z "$actors" ] || actor_args=(--actors "$actors")

if [ -n "$cell" ]; then
  run="runs/$name"
  mkdir -p "$run"
  if [ -z "$train_cycles" ]; then
    train_cycles="$("$bin/bcal" calibrate --data "$data" --cell "$cell" --print-train-cycles)"
  fi
  # The doctor chooses the model on the training cycles alone: it fits their first three quarters and
  # judges the candidates on the last quarter (the cycles calibrate judges later are never looked at).
  case "$train_cycles" in
    *..*) first="${train_cycles%%..*}"; last="${train_cycles##*..}" ;;
    *) echo "run.sh: --train-cycles must read A..B" >&2; exit 2 ;;
  esac
  case "$first$last" in ''|*[!0-9]*) echo "run.sh: --train-cycles must read A..B with whole numbers" >&2; exit 2 ;; esac
  [ $((last - first)) -ge 7 ] || { echo "run.sh: --train-cycles needs at least 8 cycles" >&2; exit 2; }
  split=$((first + (last - first + 1) * 3 / 4))
  echo "== diagnose the training cycles of $cell (fit $first..$((split - 1)), judge $split..$last)"
  "$bin/bcal" diagnose --data "$data" --cell "$cell" --cycles "$first..$((split - 1))" --holdout "$split..$last" \
    "${cutoff_args[@]}" --out "$run/diagnosis"
  echo "== the cell's training setting (on the diagnosed model)"
  "$bin/bcal" cell-config --data "$data" --cell "$cell" --train-cycles "$train_cycles" --model "$run/diagnosis" \
    "${cutoff_args[@]}" --budget-s "$budget_s" --out "$run/cell.toml"
  echo "== train (the cell's setting, budget ${budget_s} s)"
  "$bin/bcal" train --config "$run/cell.toml" --seed 1 "${actor_args[@]}" --run "$run/train"
  echo "== calibrate the held-out cycles"
  "$bin/bcal" calibrate --data "$data" --cell "$cell" --train-cycles "$train_cycles" --model "$run/diagnosis" \
    "${cutoff_args[@]}" --calibrator "rl:$run/train,ukf,adaptive_ukf,fit" --out "$run/calibration"
  echo
  echo "report: $run/calibration/calibration.md (calibration.json, plots, readings/); diagnosis: $run/diagnosis/diagnosis.md"
  exit 0
fi
if [ "$preset" != measured ]; then
  echo "== data set"
  "$bin/bcal" dataset generate --experiment "$experiment"
fi

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
