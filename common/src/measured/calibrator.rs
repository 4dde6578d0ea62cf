//! One step interface for every calibrator that reads a cell as a BMS does, so the same code serves the
//! simulator (the evaluator, with the truth known) and real data (`bcal calibrate`): a reading in, the
//! parameter estimate, its 90 % interval and the calibrated model state out. Implementations here need no
//! libtorch: the RL policy ([`RlCalibrator`], the pure-Rust forward pass), the calibrator's own fit without
//! learning ([`WindowFitCalibrator`], the ablation that shows what the policy adds to its features) and
//! the uncalibrated model ([`Uncalibrated`]). The joint UKF and the direct mapping live in bcal-eval.

use super::scenario::Sample;
use super::tracker::{ActionMode, Interval, Tracker, TrackerSpec, OBS_DIM};
use crate::battery::{BatteryModel, Degradation, Load, LoadProfile};
use crate::math::ModelState;
use crate::policy::{PolicyNet, Scratch};

/// A calibrator fed one reading at a time, in time order, with no look-ahead.
pub trait Calibrator {
    /// Takes the next reading.
    fn step(&mut self, s: &Sample);
    /// The current estimate.
    fn estimate(&self) -> Degradation;
    /// The 90 % interval of the estimate (None while the calibrator cannot tell).
    fn interval(&self) -> Option<Interval>;
    /// The calibrated model state now (for end-of-discharge predictions); None before the first reading.
    fn state(&self) -> Option<ModelState>;
    /// The model state now as it would be under parameters `d` (the bounds of an interval): a calibrator
    /// that keeps its state consistent with any parameters rebuilds it; others give their own state.
    fn state_under(&self, _d: &Degradation) -> Option<ModelState> {
        self.state()
    }
}

/// What a calibrator built on a [`Tracker`] (field `tracker`) answers: the tracker's estimate, its interval
/// (or none) and the model state under any parameters.
macro_rules! tracker_calibrator {
    () => {
        fn interval(&self) -> Option<Interval> {
            self.tracker.interval()
        }
        tracker_calibrator!(@state);
    };
    (no_interval) => {
        fn interval(&self) -> Option<Interval> {
            None
        }
        tracker_calibrator!(@state);
    };
    (@state) => {
        fn estimate(&self) -> Degradation {
            self.tracker.estimate()
        }
        fn state(&self) -> Option<ModelState> {
            tracker_state(&self.tracker)
        }
        fn state_under(&self, d: &Degradation) -> Option<ModelState> {
            self.tracker.cell().map(|c| c.state(&c.track, d))
        }
    };
}

/// The RL policy as a calibrator: its tracker reads, the policy's deterministic action moves the estimate.
pub struct RlCalibrator<'a> {
    tracker: Tracker,
    net: &'a PolicyNet,
    scratch: Scratch,
    obs: [f32; OBS_DIM],
}

impl<'a> RlCalibrator<'a> {
    pub fn new(spec: &TrackerSpec, net: &'a PolicyNet) -> Self {
        Self { tracker: Tracker::new(spec), scratch: Scratch::new(net.layout()), net, obs: [0.0; OBS_DIM] }
    }

    pub fn tracker(&self) -> &Tracker {
        &self.tracker
    }
}

impl Calibrator for RlCalibrator<'_> {
    fn step(&mut self, s: &Sample) {
        self.tracker.ingest(s);
        self.tracker.observe(&mut self.obs);
        let mut a = [0f32; 2];
        self.net.act_deterministic(&self.obs, &mut self.scratch, &mut a);
        self.tracker.apply_action(&a);
    }
    tracker_calibrator!();
}

/// The tracker following its own fit step (as far as `step_max` allows per reading), no learning.
pub struct WindowFitCalibrator {
    tracker: Tracker,
}

impl WindowFitCalibrator {
    pub fn new(spec: &TrackerSpec) -> Self {
        // The fit's own step is a zero residual action, whatever the policy's action mode.
        Self { tracker: Tracker::new(&TrackerSpec { action: ActionMode::Residual, ..spec.clone() }) }
    }

    pub fn tracker(&self) -> &Tracker {
        &self.tracker
    }
}

impl Calibrator for WindowFitCalibrator {
    fn step(&mut self, s: &Sample) {
        self.tracker.ingest(s);
        self.tracker.apply_action(&[0.0, 0.0]);
    }
    tracker_calibrator!();
}

/// A model that never calibrates during the discharge: parameters fixed from the start (the prior, a new
/// cell's, the previous cycle's or an offline fit's), its state from the readings.
pub struct Uncalibrated {
    tracker: Tracker,
}

impl Uncalibrated {
    /// At the spec's prior.
    pub fn new(spec: &TrackerSpec) -> Self {
        Self { tracker: Tracker::new(spec) }
    }

    /// At `d` (clamped to the spec's ranges).
    pub fn pinned(spec: &TrackerSpec, d: &Degradation) -> Self {
        let mut tracker = Tracker::new(spec);
        tracker.set_estimate(d);
        Self { tracker }
    }
}

impl Calibrator for Uncalibrated {
    fn step(&mut self, s: &Sample) {
        self.tracker.ingest(s);
    }
    tracker_calibrator!(no_interval);
}

/// The model state of a tracker under its current estimate.
pub fn tracker_state(t: &Tracker) -> Option<ModelState> {
    t.cell().map(|c| c.state(&c.track, &t.estimate()))
}

/// How an end-of-discharge prediction runs: the future load (in the episode's absolute time), the cut-off,
/// the Euler step and the longest horizon.
#[derive(Clone, Debug)]
pub struct EodQuery<'a> {
    pub profile: &'a LoadProfile,
    pub cutoff_v: f64,
    pub dt_s: f64,
    pub max_s: f64,
}

/// Predicted end-of-discharge time, s: the model runs from `x` at time `t_now_s` under `d` and the query's
/// load until the voltage falls below its cut-off, or until the model itself is empty: a surface mole
/// fraction at its clip ([`crate::battery::MOLE_FRACTION_CLIP`]), where the model's voltage stops falling
/// (about 3.0 V at 2 A) while a real cell drops through its knee to any lower cut-off within a minute or
/// two (NASA B0005: 3.0 V to 2.7 V in 47 s of a 3160 s discharge). None when neither happens within
/// `max_s` or the model fails.
pub fn predict_eod_s(model: &BatteryModel, x: &ModelState, d: &Degradation, t_now_s: f64, q: &EodQuery) -> Option<f64> {
    let (profile, cutoff_v, dt_s) = (q.profile, q.cutoff_v, q.dt_s);
    let mut x = *x;
    let mut t = t_now_s;
    while t - t_now_s <= q.max_s {
        let v = model.voltage_v(&x, d);
        if !v.is_finite() {
            return None;
        }
        if v < cutoff_v || model.surface_empty(&x, d) {
            return Some(t);
        }
        let i = match profile.at(t) {
            Load::CurrentA(a) => a,
            Load::PowerW(w) => w / v,
        };
        x = model.step_current(&x, i, dt_s, d);
        t += dt_s;
    }
    None
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::battery::BatteryParams;
    use crate::dataset::Split;
    use crate::measured::scenario::{draw_spec, simulate, ScenarioConfig};
    use rand::SeedableRng;

    /// From the true state and parameters the prediction is the true end of discharge (same model, same
    /// step), and an uncalibrated model's is not.
    #[test]
    fn eod_from_the_truth_is_the_truth() {
        let cfg = ScenarioConfig { sensor: Default::default(), ..Default::default() };
        let mut rng = rand::rngs::SmallRng::seed_from_u64(9);
        let spec = draw_spec(&cfg, Split::Test, &mut rng);
        let ep = simulate(&cfg, &spec).unwrap();
        let model = BatteryModel::new(BatteryParams::default(), false).unwrap();
        let xn = crate::measured::scenario::xn_of_soc(&model.params, spec.soc0);
        let x0 = crate::measured::scenario::rest_state(&model, &spec.truth, xn, model.params.tb0_k);
        let q = EodQuery { profile: &spec.profile, cutoff_v: 3.0, dt_s: 1.0, max_s: 1e5 };
        let eod = predict_eod_s(&model, &x0, &spec.truth, 0.0, &q).unwrap();
        assert_eq!(Some(eod), ep.eod_s);
        let mut unc = Uncalibrated::new(&TrackerSpec::default());
        for s in &ep.samples {
            unc.step(s);
        }
        assert_eq!(unc.estimate(), TrackerSpec::default().prior);
        let at = Degradation { q_mobile_c: 5000.0, r_o_ohm: 0.12 };
        let mut pinned = Uncalibrated::pinned(&TrackerSpec::default(), &at);
        for s in &ep.samples {
            pinned.step(s);
        }
        assert!(
            (pinned.estimate().q_mobile_c - 5000.0).abs() < 1e-9 && (pinned.estimate().r_o_ohm - 0.12).abs() < 1e-12
        );
        assert!(unc.interval().is_none() && unc.state().is_some());
    }
}
