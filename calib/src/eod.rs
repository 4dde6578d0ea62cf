//! End-of-discharge prediction from a calibrated state: the model run forward under a load until the
//! cut-off (or until it is empty).

use bcal_common::battery::{BatteryModel, Degradation, Load, LoadProfile};
use bcal_common::math::ModelState;
use bcal_common::measured::scenario::Sample;

/// The charge a discharge's readings drew from the first of `samples` to `end_s`, Ah: the discharging
/// current (charging counts 0) by the trapezoid rule, the interval holding `end_s` cut there with the
/// current taken linear in it. With `end_s` the interpolated cut-off crossing this is the discharge's
/// measured capacity, not the charge to the first reading below the cut-off (a sample interval, 10-20 s on
/// a NASA cycler, past it): `bcal calibrate`'s records and a live stream both measure it so.
pub fn charge_to_ah(samples: &[Sample], end_s: f64) -> f64 {
    let mut q_c = 0.0;
    for w in samples.windows(2) {
        let (a, b) = (&w[0], &w[1]);
        let (i0, i1) = (a.current_a.max(0.0), b.current_a.max(0.0));
        if b.t_s <= end_s {
            q_c += drawn_between_c(a, b);
        } else {
            if a.t_s < end_s {
                let f = (end_s - a.t_s) / (b.t_s - a.t_s);
                q_c += 0.5 * (i0 + (i0 + f * (i1 - i0))) * (end_s - a.t_s);
            }
            break;
        }
    }
    q_c / 3600.0
}

/// The charge drawn from reading `a` to reading `b`, C: the discharging current (charging counts 0) by the
/// trapezoid rule ([`charge_to_ah`]'s, and a live stream's charge drawn so far).
pub fn drawn_between_c(a: &Sample, b: &Sample) -> f64 {
    0.5 * (a.current_a.max(0.0) + b.current_a.max(0.0)) * (b.t_s - a.t_s)
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
/// fraction at its clip ([`bcal_common::battery::MOLE_FRACTION_CLIP`]), where the model's voltage stops falling
/// (about 3.0 V at 2 A) while a real cell drops through its knee to any lower cut-off within a minute or
/// two (NASA B0005: 3.0 V to 2.7 V in 47 s of a 3160 s discharge). None when neither happens within
/// `max_s` or the model fails.
pub fn predict_eod_s(model: &BatteryModel, x: &ModelState, d: &Degradation, t_now_s: f64, q: &EodQuery) -> Option<f64> {
    predict_eod(model, x, d, t_now_s, q).map(|p| p.eod_s)
}

/// A predicted end of discharge: its time, s, and the charge the model drew from the prediction's start to
/// it, C (under a power load the current rises as the voltage falls).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct EodPrediction {
    pub eod_s: f64,
    pub drawn_c: f64,
}

impl EodPrediction {
    /// The mean current from `t_now_s` to the end, A (the load's own current under a constant one; None
    /// when the end is now).
    pub fn mean_current_a(&self, t_now_s: f64) -> Option<f64> {
        (self.eod_s > t_now_s).then(|| self.drawn_c / (self.eod_s - t_now_s))
    }
}

/// [`predict_eod_s`] with the charge drawn on the way.
pub fn predict_eod(
    model: &BatteryModel,
    x: &ModelState,
    d: &Degradation,
    t_now_s: f64,
    q: &EodQuery,
) -> Option<EodPrediction> {
    let (profile, cutoff_v, dt_s) = (q.profile, q.cutoff_v, q.dt_s);
    let mut x = *x;
    let mut t = t_now_s;
    let mut drawn_c = 0.0;
    while t - t_now_s <= q.max_s {
        let v = model.voltage_v(&x, d);
        if !v.is_finite() {
            return None;
        }
        if v < cutoff_v || model.surface_empty(&x, d) {
            return Some(EodPrediction { eod_s: t, drawn_c });
        }
        let i = match profile.at(t) {
            Load::CurrentA(a) => a,
            Load::PowerW(w) => w / v,
        };
        x = model.step_current(&x, i, dt_s, d);
        drawn_c += i * dt_s;
        t += dt_s;
    }
    None
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{Calibrator, Uncalibrated};
    use bcal_common::battery::BatteryParams;
    use bcal_common::dataset::Split;
    use bcal_common::measured::scenario::{draw_spec, simulate, ScenarioConfig};
    use bcal_common::measured::tracker::TrackerSpec;
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
        let xn = bcal_common::measured::scenario::xn_of_soc(&model.params, spec.soc0);
        let x0 = bcal_common::measured::scenario::rest_state(&model, &spec.truth, xn, model.params.tb0_k);
        let q = EodQuery { profile: &spec.profile, cutoff_v: 3.0, dt_s: 1.0, max_s: 1e5 };
        let eod = predict_eod_s(&model, &x0, &spec.truth, 0.0, &q).unwrap();
        assert_eq!(Some(eod), ep.eod_s);
        // The charge on the way is the simulated cell's: the current it drew step by step to its end.
        let mut drawn_c = 0.0;
        model
            .simulate_until_eod(&x0, &spec.truth, &spec.profile, 1.0, 100_000, |r| {
                if r.t_s < eod {
                    drawn_c += r.current_a;
                }
            })
            .unwrap();
        let p = predict_eod(&model, &x0, &spec.truth, 0.0, &q).unwrap();
        assert!((p.drawn_c - drawn_c).abs() < 1e-9 * drawn_c.max(1.0), "{} against {drawn_c}", p.drawn_c);
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
