//! Analysis behind docs/evaluator.md (`cargo run --release -p bcal-calib --example load_rule [N]`): what the
//! load a prediction assumes costs the end of discharge on the simulated test cells, apart from calibration.
//! Each of the first N test cells (96) of the default measured setting is predicted from its own true state
//! and parameters at 10, 50 and 90 % of its discharge, under three loads: the rule every prediction uses
//! (`LoadMean::load`: the loaded readings' mean current, over time where the load alternates, or their mean
//! power where it has been held at power), the loaded readings' mean current alone, and the cell's true
//! future load (the oracle). The error left is the load's alone (the model and state are exact), per kind of
//! load: absolute error, mean and median, s, and how many predictions assumed a power.
use bcal_calib::{predict_eod_s, EodQuery};
use bcal_common::battery::{BatteryModel, BatteryParams, Load, LoadProfile};
use bcal_common::dataset::Split;
use bcal_common::math::idx;
use bcal_common::measured::env::MeasuredSpec;
use bcal_common::measured::scenario::{episode_set, rest_state, xn_of_soc, Episode, LoadKind};
use bcal_common::measured::LoadMean;
use std::collections::BTreeMap;

const FRACTIONS: [f64; 3] = [0.1, 0.5, 0.9];

/// Per (kind of load, fraction): the absolute errors under the rule, the mean current and the oracle, s, and
/// how many predictions assumed a power.
type Table = BTreeMap<(String, usize), ([Vec<f64>; 3], usize)>;

/// The cell's true state at each time of `at` (sorted), stepped as the simulator steps it.
fn true_states(e: &Episode, model: &BatteryModel, dt_s: f64, at: &[f64]) -> Vec<[f64; 8]> {
    let mut x = rest_state(model, &e.spec.truth, xn_of_soc(&model.params, e.spec.soc0), e.spec.ambient_k);
    let (mut t_s, mut out) = (0.0, Vec::new());
    for &a in at {
        while t_s + 1e-9 < a {
            let v = model.voltage_v(&x, &e.spec.truth);
            let i = match e.spec.profile.at(t_s) {
                Load::CurrentA(c) => c,
                Load::PowerW(w) => w / v,
            };
            x = model.step_current(&x, i, dt_s, &e.spec.truth);
            t_s += dt_s;
        }
        let mut y = [0.0; 8];
        y.copy_from_slice(x.as_slice());
        out.push(y);
    }
    out
}

fn main() {
    let n: usize = std::env::args().nth(1).map_or(96, |a| a.parse().expect("N: a number of cells"));
    let cfg = MeasuredSpec::default().scenario;
    assert!(!cfg.model.temperature_dependent() && cfg.model == Default::default(), "the base model");
    let cells = episode_set(&cfg, Split::Test, n).expect("the test cells simulate");
    let mut table = Table::new();
    for e in &cells {
        let Some(end_s) = e.eod_s else { continue };
        let params = BatteryParams { tb0_k: e.spec.ambient_k, ..cfg.model.params() };
        let model = BatteryModel::new(params, cfg.thermal).expect("the default cell");
        let start = e.spec.rest_s;
        let at: Vec<f64> = FRACTIONS.iter().map(|f| start + f * (end_s - start)).collect();
        // The prediction is made at the first reading at or after each time, from the state there.
        let mut load = LoadMean::default();
        let (mut next, mut made) = (0, Vec::new());
        for s in &e.samples {
            load.push(s.t_s, s.current_a, s.voltage_v);
            while next < at.len() && s.t_s >= at[next] {
                made.push((s.t_s, load, load.loaded_mean_a()));
                next += 1;
            }
        }
        let times: Vec<f64> = made.iter().map(|m| m.0).collect();
        let states = true_states(e, &model, cfg.truth_dt_s, &times);
        let kind = match e.spec.kind {
            LoadKind::ConstantPower => "constant power",
            LoadKind::ConstantCurrent => "constant current",
            LoadKind::Piecewise => "piecewise power",
        };
        for (k, ((t_s, mean, loaded_a), y)) in made.iter().zip(&states).enumerate() {
            let x = bcal_common::math::ModelState::from_column_slice(y);
            debug_assert!(x[idx::T_B] > 0.0);
            let predict = |profile: LoadProfile| {
                let q = EodQuery { profile: &profile, cutoff_v: cfg.cutoff_v, dt_s: 1.0, max_s: 4.0 * (end_s + 100.0) };
                predict_eod_s(&model, &x, &e.spec.truth, *t_s, &q).map(|p| (p - end_s).abs())
            };
            let entry = table.entry((kind.to_string(), k)).or_default();
            let loads = [mean.load(), loaded_a.map(Load::CurrentA)];
            for (j, l) in loads.into_iter().enumerate() {
                if let Some(err) = l.and_then(|l| predict(LoadProfile::Constant(l))) {
                    entry.0[j].push(err);
                }
            }
            if let Some(err) = predict(e.spec.profile.clone()) {
                entry.0[2].push(err);
            }
            entry.1 += usize::from(matches!(mean.load(), Some(Load::PowerW(_))));
        }
    }
    println!(
        "| load | at | cells | power assumed | rule: MAE / median s | mean current: MAE / median s | oracle: MAE / \
         median s |"
    );
    println!("| --- | ---: | ---: | ---: | ---: | ---: | ---: |");
    let stats = |v: &[f64]| {
        let mut s = v.to_vec();
        s.sort_by(f64::total_cmp);
        let mean = s.iter().sum::<f64>() / s.len().max(1) as f64;
        let median = s.get(s.len() / 2).copied().unwrap_or(f64::NAN);
        format!("{mean:.1} / {median:.1}")
    };
    for ((kind, k), (errs, powers)) in &table {
        println!(
            "| {kind} | {:.0} % | {} | {powers} | {} | {} | {} |",
            100.0 * FRACTIONS[*k],
            errs[2].len(),
            stats(&errs[0]),
            stats(&errs[1]),
            stats(&errs[2])
        );
    }
}
