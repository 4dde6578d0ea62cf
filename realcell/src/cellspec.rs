//! The measured-only setting of one real cell, derived from its training cycles alone (nothing tuned to a
//! particular cell): the load (constant current at the cycles' current, or constant power at their power
//! where most of them held a power: `bcal_common::measured::LoadMean`), the sampling the data has, the
//! rest before each discharge, the starting charge, the ambient temperature with a self-heating cell, the
//! cut-off, and parameter ranges around the doctor's fits of the training cycles, widened for the ageing
//! still to come. An RL policy for the cell trains on cells drawn from it; the joint UKF is tuned on its
//! validation cells; both read the cell's measured temperature.

use crate::record::CellRecord;
use bcal_common::battery::{Degradation, Load};
use bcal_common::measured::env::MeasuredSpec;
use bcal_common::measured::extension::ModelExtension;
use bcal_common::measured::scenario::{LoadKind, ScenarioConfig, SplitLoads, KELVIN_0C};
use bcal_common::measured::tracker::TrackerSpec;
use serde::Serialize;

/// How far the parameter ranges reach beyond the training fits: a cell keeps losing capacity and gaining
/// resistance after its training cycles (NASA cells lose 30 % of their capacity over their life), so the
/// true qMobile may fall to `Q_AGEING_FLOOR` of the smallest fit and Ro rise to `R_AGEING_CEILING` times the
/// largest.
pub const Q_AGEING_FLOOR: f64 = 0.5;
pub const R_AGEING_CEILING: f64 = 2.5;

/// What the derivation read off the training cycles, for the report.
#[derive(Clone, Debug, Serialize)]
pub struct CellFacts {
    /// The training records' median current, A, and the lowest and highest (the simulated cells' range).
    pub current_a: f64,
    pub current_range_a: [f64; 2],
    /// The training records' median power, W, where most of them held a power (None: a current).
    pub power_w: Option<f64>,
    pub interval_s: [f64; 2],
    pub rest_s: [f64; 2],
    /// The training records' median ambient, deg C, and the lowest and highest.
    pub ambient_c: f64,
    pub ambient_range_c: [f64; 2],
    pub fit_q_mobile_c: [f64; 2],
    pub fit_r_o_ohm: [f64; 2],
}

fn quantile(mut v: Vec<f64>, q: f64) -> f64 {
    bcal_common::stats::quantile(&mut v, q).unwrap_or(f64::NAN)
}

/// The lowest and highest of `v`.
fn span(v: Vec<f64>) -> [f64; 2] {
    [quantile(v.clone(), 0.0), quantile(v, 1.0)]
}

/// The cell's measured-only setting from its training records and their fits (each with its model: the
/// base one, or the doctor's extended one with the cycle's values). The simulated cells and the
/// calibrator run the model of the last training cycle, at the cell's ambient, following the measured
/// temperature when the model has the doctor's `thermal` (isothermal at the ambient otherwise, as the
/// doctor runs it).
pub fn cell_spec(
    train: &[CellRecord],
    fits_with_models: &[(Degradation, ModelExtension)],
    cutoff_v: f64,
) -> (MeasuredSpec, CellFacts) {
    let fits: Vec<Degradation> = fits_with_models.iter().map(|f| f.0).collect();
    // Simulated cells are drawn across every current, power and ambient the training cycles held (a cell
    // cycled at 1, 2 and 4 A, or at 24 and 44 C, trains on all of them), 5 % and 1 K beyond.
    let currents: Vec<f64> = train.iter().map(|r| r.current_a).collect();
    let (current_a, current_range_a) = (quantile(currents.clone(), 0.5), span(currents));
    let intervals: Vec<f64> =
        train.iter().flat_map(|r| r.samples.windows(2).map(|w| w[1].t_s - w[0].t_s)).filter(|d| *d > 0.0).collect();
    let interval_s = [quantile(intervals.clone(), 0.1).round().max(1.0), quantile(intervals, 0.9).round().max(1.0)];
    let rests: Vec<f64> = train.iter().map(|r| r.load_on_s - r.samples[0].t_s).collect();
    let rest_s = [quantile(rests.clone(), 0.1).clamp(1.0, 600.0), quantile(rests, 0.9).clamp(1.0, 600.0)];
    let ambients: Vec<f64> = train.iter().map(|r| r.ambient_k - KELVIN_0C).collect();
    let (ambient_c, ambient_range_c) = (quantile(ambients.clone(), 0.5), span(ambients));
    let model = ModelExtension {
        reference_k: Some(ambient_c + KELVIN_0C),
        ..fits_with_models.last().map(|f| f.1.clone()).unwrap_or_default()
    };
    let thermal = model.has("thermal");
    let qs: Vec<f64> = fits.iter().map(|d| d.q_mobile_c).collect();
    let rs: Vec<f64> = fits.iter().map(|d| d.r_o_ohm).collect();
    let (q_lo, q_hi) = (quantile(qs.clone(), 0.0), quantile(qs.clone(), 1.0));
    let (r_lo, r_hi) = (quantile(rs.clone(), 0.0), quantile(rs.clone(), 1.0));
    // Data ranges: what the cell may be over the rest of its life; estimate ranges a little wider.
    let q_data = [Q_AGEING_FLOOR * q_lo, 1.05 * q_hi];
    let r_data = [(0.5 * r_lo).max(0.005), R_AGEING_CEILING * r_hi.max(0.01)];
    // A cell most of whose training discharges held a power trains at it: at its current, the simulated
    // cells' current would not rise as their voltage falls, and the policy would learn another cell's end.
    let powers: Vec<f64> = train
        .iter()
        .filter_map(|r| match r.load() {
            Load::PowerW(w) => Some(w),
            Load::CurrentA(_) => None,
        })
        .collect();
    let power_w = (2 * powers.len() > train.len()).then(|| quantile(powers.clone(), 0.5));
    let (load_kind, power_range_w) = match power_w {
        Some(_) => {
            let [lo, hi] = span(powers);
            (LoadKind::ConstantPower, [0.95 * lo, 1.05 * hi])
        }
        None => (LoadKind::ConstantCurrent, [1.0, 1.0]),
    };
    let loads =
        SplitLoads { power_w: power_range_w, current_a: [0.95 * current_range_a[0], 1.05 * current_range_a[1]] };
    let scenario = ScenarioConfig {
        q_mobile_c: q_data,
        r_o_ohm: r_data,
        // A cycler charges the cell full before each discharge; a little slack for self-discharge.
        soc0: [0.95, 1.0],
        rest_s,
        sample_interval_s: vec![interval_s],
        load_kinds: vec![load_kind],
        train: loads.clone(),
        validation: loads.clone(),
        test: loads,
        thermal,
        ambient_c: [ambient_range_c[0] - 1.0, ambient_range_c[1] + 1.0],
        cutoff_v,
        model: model.clone(),
        ..ScenarioConfig::default()
    };
    let tracker = TrackerSpec {
        q_mobile_range_c: [0.9 * q_data[0], 1.1 * q_data[1]],
        r_o_range_ohm: [0.5 * r_data[0], 1.1 * r_data[1]],
        prior: Degradation { q_mobile_c: quantile(qs, 0.5), r_o_ohm: quantile(rs, 0.5) },
        use_measured_temperature: thermal,
        cutoff_v,
        model,
        ..TrackerSpec::default()
    };
    let facts = CellFacts {
        current_a,
        current_range_a,
        power_w,
        interval_s,
        rest_s,
        ambient_c,
        ambient_range_c,
        fit_q_mobile_c: [q_lo, q_hi],
        fit_r_o_ohm: [r_lo, r_hi],
    };
    (MeasuredSpec { scenario, tracker, ..MeasuredSpec::default() }, facts)
}

#[cfg(test)]
mod tests {
    use super::*;
    use bcal_common::measured::scenario::{Request, Sample};

    #[test]
    fn the_setting_follows_the_training_cycles_and_validates() {
        let rec = |cycle: u32, dt: f64| {
            let samples: Vec<Sample> = (0..200)
                .map(|k| Sample {
                    t_s: dt * k as f64,
                    voltage_v: 4.0,
                    current_a: if k < 2 { 0.0 } else { 2.0 },
                    temperature_k: 297.15,
                    request: Request::Unknown,
                })
                .collect();
            CellRecord {
                cell: "T".into(),
                cycle,
                source: "t".into(),
                load_on_s: 2.0 * dt,
                eod_s: Some(199.0 * dt),
                current_a: 2.0,
                data_capacity_ah: Some(1.8),
                stated_capacity_ah: Some(1.8),
                ambient_k: 297.15,
                rest_before_s: None,
                current_before_a: None,
                partial_start: false,
                short_start_seen: false,
                partial_start_seen: false,
                start_share_sd: None,
                stated_tail_ah: None,
                samples,
            }
        };
        let train = vec![rec(1, 18.0), rec(2, 10.0), rec(3, 18.0)];
        let base = ModelExtension::default();
        let fits = vec![
            (Degradation { q_mobile_c: 7000.0, r_o_ohm: 0.10 }, base.clone()),
            (Degradation { q_mobile_c: 6800.0, r_o_ohm: 0.12 }, base.clone()),
            (Degradation { q_mobile_c: 6600.0, r_o_ohm: 0.14 }, base),
        ];
        let (spec, facts) = cell_spec(&train, &fits, 2.7);
        assert_eq!(facts.current_a, 2.0);
        assert_eq!(facts.interval_s, [10.0, 18.0]);
        assert!((facts.ambient_c - 24.0).abs() < 1e-9);
        assert_eq!(spec.scenario.q_mobile_c, [3300.0, 7350.0]);
        assert_eq!(spec.tracker.prior, Degradation { q_mobile_c: 6800.0, r_o_ohm: 0.12 });
        // The base model runs isothermal at the cell's ambient, as the doctor runs it.
        assert!(!spec.tracker.use_measured_temperature && !spec.scenario.thermal);
        assert_eq!(spec.tracker.model.reference_k, Some(297.15));
        // A run config over the measured preset with this setting passes the config's checks.
        let mut c = bcal_common::config::Preset::Measured.config();
        c.measured = spec;
        c.validate().unwrap();
        assert_eq!((facts.power_w, &c.measured.scenario.load_kinds[..]), (None, &[LoadKind::ConstantCurrent][..]));

        // Training cycles at two currents and two ambients (2 A at 24 C, 4 A at 43 C): the simulated cells are
        // drawn across both, not around the median alone (which left half the cycles unseen).
        let mut mixed = train.clone();
        mixed.push(CellRecord { cycle: 4, current_a: 4.0, ambient_k: 316.15, ..rec(4, 18.0) });
        mixed.push(CellRecord { cycle: 5, current_a: 4.0, ambient_k: 316.15, ..rec(5, 18.0) });
        let fits5 = [fits.clone(), fits[1..].to_vec()].concat();
        let (spec, facts) = cell_spec(&mixed, &fits5, 2.7);
        assert_eq!((facts.current_a, facts.current_range_a), (2.0, [2.0, 4.0]));
        assert!((facts.ambient_range_c[0] - 24.0).abs() < 1e-9 && (facts.ambient_range_c[1] - 43.0).abs() < 1e-9);
        for split in [&spec.scenario.train, &spec.scenario.validation, &spec.scenario.test] {
            assert!((split.current_a[0] - 1.9).abs() < 1e-12 && (split.current_a[1] - 4.2).abs() < 1e-12, "{split:?}");
        }
        let [lo, hi] = spec.scenario.ambient_c;
        assert!((lo - 23.0).abs() < 1e-9 && (hi - 44.0).abs() < 1e-9, "{:?}", spec.scenario.ambient_c);
        c.measured = spec;
        c.validate().unwrap();
    }

    /// Training discharges held at constant power (7.5 W, the simulator's cell) give a setting of simulated
    /// cells at that power, which the config's checks pass.
    #[test]
    fn a_cell_discharged_at_constant_power_trains_at_its_power() {
        let cfg = ScenarioConfig { cutoff_v: 2.5, ..Default::default() };
        let truth = Degradation { q_mobile_c: 7200.0, r_o_ohm: 0.12 };
        let train: Vec<CellRecord> = (1..=3)
            .map(|c| crate::testing::simulated_record_under(&cfg, truth, 1.0, u64::from(c), c, Load::PowerW(7.5)))
            .collect();
        let fits = vec![(truth, ModelExtension::default()); 3];
        let (spec, facts) = cell_spec(&train, &fits, 2.5);
        let w = facts.power_w.expect("a power");
        assert!((w - 7.5).abs() < 0.05, "{w} W");
        assert_eq!(spec.scenario.load_kinds, vec![LoadKind::ConstantPower]);
        for range in [spec.scenario.train.power_w, spec.scenario.validation.power_w, spec.scenario.test.power_w] {
            assert!(range[0] < 7.5 && 7.5 < range[1], "{range:?}");
        }
        let mut c = bcal_common::config::Preset::Measured.config();
        c.measured = spec;
        c.validate().unwrap();
    }
}
