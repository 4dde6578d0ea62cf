//! What a measured-only calibrator owns and sees, one reading at a time: its own cell model
//! ([`CellModel`]), its current parameter estimate, the fit window over recent readings, and the
//! observation assembled from them. The RL environment, the learner's validation, the evaluator and
//! `bcal calibrate` on real data all drive this one type, so a policy meets exactly the features it was
//! trained on.
//!
//! Per reading: [`Tracker::ingest`] advances the model from the previous reading (the load read then held,
//! a switch put at mid-interval: [`bcal_common::measured::cellmodel::interval_drive`]; the starting charge from the rest
//! voltage until the load starts; with `fit_start` its uncertainty enters the fit's information, and a start
//! no rest was read for is fitted with the parameters, moved by the fit's own step after every action), adds
//! the reading
//! to the window; [`Tracker::observe`] writes the observation; the policy's action moves the estimate by
//! at most `step_max` of the range ([`Tracker::apply_action`]). The RL cost of that action is the window's
//! RMS residual under the new estimate once the next reading is in ([`Tracker::cost`]): how well the
//! estimate explains what was measured, with no true parameter and no true state.

use crate::window::{FitPoint, FitStats, FitWindow, StartPrior};
use crate::Interval;
use bcal_common::battery::{BatteryModel, Degradation};
use bcal_common::measured::cellmodel::{start_xn_std, xn_from_rest_voltage, CellModel, Settle, REST_CURRENT_A};
use bcal_common::measured::scenario::{Request, Sample};
use bcal_common::measured::tracker::{ActionMode, TrackerSpec, OBS_DIM};

/// The calibrator's state along one discharge.
#[derive(Clone, Debug)]
pub struct Tracker {
    spec: TrackerSpec,
    cell: Option<CellModel>,
    window: FitWindow,
    z: [f64; 2],
    last: Option<Sample>,
    /// Rest voltages summed before the load started (for the starting charge).
    rest_sum_v: f64,
    rest_n: u32,
    loaded: bool,
    /// The starting charge's prior, set when the load starts (with `fit_start`).
    start_prior: Option<StartPrior>,
    /// The fit's step of the starting charge after the last action, applied before the next reading.
    pending_start: f64,
    start_t_s: f64,
    /// Time since the previous reading, s (0 at the first).
    interval_s: f64,
    readings: u64,
    /// Statistics at the current estimate, refreshed by `ingest` and `apply_action`.
    stats: FitStats,
    settle: Settle,
}

impl Tracker {
    pub fn new(spec: &TrackerSpec) -> Self {
        Self {
            z: spec.to_z(&spec.prior),
            window: FitWindow::new(spec.window_points, spec.window_span_s),
            spec: spec.clone(),
            cell: None,
            last: None,
            rest_sum_v: 0.0,
            rest_n: 0,
            loaded: false,
            start_prior: None,
            pending_start: 0.0,
            start_t_s: 0.0,
            interval_s: 0.0,
            readings: 0,
            stats: FitStats::default(),
            settle: Settle::default(),
        }
    }

    pub fn spec(&self) -> &TrackerSpec {
        &self.spec
    }

    /// The current estimate.
    pub fn estimate(&self) -> Degradation {
        self.spec.from_z(self.z)
    }

    /// The calibrator's model (None before the first reading).
    pub fn cell(&self) -> Option<&CellModel> {
        self.cell.as_ref()
    }

    pub fn stats(&self) -> &FitStats {
        &self.stats
    }

    fn temperature_of(&self, s: &Sample, model: &BatteryModel) -> f64 {
        if self.spec.use_measured_temperature {
            s.temperature_k
        } else {
            model.params.tb0_k
        }
    }

    /// Takes one reading (readings in time order).
    pub fn ingest(&mut self, s: &Sample) {
        let d = self.estimate();
        self.readings += 1;
        let mut unsettled = false;
        match (&mut self.cell, self.last) {
            (None, _) => {
                let model = self.spec.model.model().expect("the config checks the model extension");
                let t_k = self.temperature_of(s, &model);
                let xn0 = xn_from_rest_voltage(&model, s.voltage_v, t_k);
                let ref_k = self.spec.model.reference_k.unwrap_or(s.temperature_k);
                self.cell = Some(
                    CellModel::at_rest(model, xn0, t_k, self.spec.max_substep_s)
                        .with_arrhenius(&self.spec.model, ref_k),
                );
                self.start_t_s = s.t_s;
            }
            (Some(cell), Some(prev)) => {
                // The start moves before the model does: the track holds what the current moved, the same
                // whatever the start, and the overpotentials follow from the moved start from here on.
                let p = &cell.model.params;
                cell.xn0 = (cell.xn0 + std::mem::take(&mut self.pending_start))
                    .clamp(p.xn_min + 0.01 * (p.xn_max - p.xn_min), p.xn_max);
                let t_k = if self.spec.use_measured_temperature { s.temperature_k } else { cell.track.t_k };
                cell.advance_between(&prev, s, &d, t_k);
                unsettled = self.settle.unsettled(&prev, s, self.spec.max_substep_s, self.spec.settle_s);
            }
            (Some(_), None) => unreachable!("a cell exists only after a reading"),
        }
        // The starting charge: the mean rest voltage before any load, read through the open-circuit curve.
        let cell = self.cell.as_mut().expect("created above");
        if !self.loaded && s.current_a.abs() < REST_CURRENT_A {
            self.rest_sum_v += s.voltage_v;
            self.rest_n += 1;
            cell.xn0 = xn_from_rest_voltage(&cell.model, self.rest_sum_v / f64::from(self.rest_n), cell.track.t_k);
        } else {
            if !self.loaded && self.spec.fit_start {
                // The rest readings' mean, known to their noise averaged over them (a discharge that starts
                // under load has no rest reading: its start is as good as unknown).
                let std = if self.rest_n == 0 {
                    0.1
                } else {
                    let v_std = self.spec.noise_floor_v / f64::from(self.rest_n).sqrt();
                    start_xn_std(&cell.model, cell.xn0, cell.track.t_k, v_std, 0.005)
                };
                // Read off a rest, the start is held (moving it cost qMobile accuracy on simulated cells, whose
                // rest voltage is exact: the loaded readings then pull it off the truth through what the
                // tracker's model approximates); a stream joined under load has no rest to hold it to.
                let moves = self.rest_n == 0;
                self.start_prior = Some(StartPrior { xn: cell.xn0, std, noise_v: self.spec.noise_floor_v, moves });
            }
            self.loaded = true;
        }
        let ranges = self.spec.ranges();
        if !unsettled {
            self.window.push(FitPoint::reading(s.t_s, cell.track, s.voltage_v), cell, &d, &ranges);
        }
        self.interval_s = self.last.map_or(0.0, |p| s.t_s - p.t_s);
        self.last = Some(*s);
        let prior = self.prior();
        let cell = self.cell.as_ref().expect("created above");
        self.stats = self.window.stats(cell, &d, &ranges, prior, self.start_prior);
    }

    /// The fit's prior: the prior estimate with `prior_std_z`, weighed as the sensor noise.
    fn prior(&self) -> Option<([f64; 2], f64, f64)> {
        (self.spec.prior_std_z > 0.0)
            .then(|| (self.spec.to_z(&self.spec.prior), self.spec.prior_std_z, self.spec.noise_floor_v))
    }

    /// Moves the estimate by `action` (each in [-1, 1]) times `step_max`, on its own or added to the window
    /// fit's step ([`ActionMode`]).
    pub fn apply_action(&mut self, action: &[f32]) {
        let m = self.spec.step_max;
        for ((z, a), fit) in self.z.iter_mut().zip(action).zip(self.stats.step) {
            let a = f64::from(a.clamp(-1.0, 1.0));
            let moved = match self.spec.action {
                ActionMode::Absolute => a,
                ActionMode::Residual => (fit / m + a).clamp(-1.0, 1.0),
            };
            *z = (*z + moved * m).clamp(0.0, 1.0);
        }
        if let Some(cell) = &self.cell {
            self.stats =
                self.window.stats(cell, &self.spec.from_z(self.z), &self.spec.ranges(), self.prior(), self.start_prior);
            // The start follows the fit at the new estimate (at most 0.02 per reading, about 3 % of charge).
            self.pending_start = self.stats.step_start.clamp(-0.02, 0.02);
        }
    }

    /// Sets the estimate directly (filters and tests).
    pub fn set_estimate(&mut self, d: &Degradation) {
        self.z = self.spec.to_z(d).map(|z| z.clamp(0.0, 1.0));
        if let Some(cell) = &self.cell {
            self.stats = self.window.stats(cell, d, &self.spec.ranges(), self.prior(), self.start_prior);
        }
    }

    /// The RL cost of the current estimate: ln(1 + r / `cost_scale_v`) with r the root of the fit's own
    /// objective per reading (squared residuals of every reading plus the prior's term): what the calibrator
    /// can know about its estimate, no true parameter and no true state. The prior keeps the cost from
    /// rewarding a jump the readings do not support yet (the estimate that minimises it is the posterior
    /// mode, not the least-squares fit of the first few readings).
    pub fn cost(&self) -> f64 {
        (self.stats.map_rms_v / self.spec.cost_scale_v).ln_1p()
    }

    /// The 90 % interval of the current estimate from the window's fit (None while it cannot tell).
    pub fn interval(&self) -> Option<Interval> {
        let sd = self.stats.std_z(self.spec.noise_floor_v)?;
        let k = self.spec.interval_scale;
        let (lo, hi) = (
            [self.z[0] - k[0] * sd[0], self.z[1] - k[1] * sd[1]],
            [self.z[0] + k[0] * sd[0], self.z[1] + k[1] * sd[1]],
        );
        let (a, b) = (self.spec.from_z(lo), self.spec.from_z(hi));
        Some(Interval { q_mobile_c: [a.q_mobile_c, b.q_mobile_c], r_o_ohm: [a.r_o_ohm, b.r_o_ohm] })
    }

    /// The observation after the latest reading, written into `out[..OBS_DIM]`.
    pub fn observe(&self, out: &mut [f32]) {
        let (Some(cell), Some(s)) = (&self.cell, &self.last) else {
            out[..OBS_DIM].fill(0.0);
            return;
        };
        let d = self.estimate();
        let st = &self.stats;
        let v_pred = cell.voltage(&d);
        let x = cell.state(&cell.track, &d);
        let q_max = cell.model.q_max_c(&d);
        let p = &cell.model.params;
        let xn_now = (x[bcal_common::math::idx::QN_B] + x[bcal_common::math::idx::QN_S]) / q_max;
        let drawn_c = -(cell.track.dq_c[2] + cell.track.dq_c[3]);
        let info_db = |h: f64| ((h.max(1e-14)).sqrt() / 1e-3).log10() / 3.0;
        let corr = st.info[1] / (st.info[0] * st.info[2]).sqrt().max(1e-30);
        let elapsed = s.t_s - self.start_t_s;
        let f = [
            2.0 * self.z[0] - 1.0,
            2.0 * self.z[1] - 1.0,
            st.step[0].clamp(-1.0, 1.0),
            st.step[1].clamp(-1.0, 1.0),
            // The fit's step in action units: the action that would take it, where it can.
            (st.step[0] / self.spec.step_max).clamp(-1.0, 1.0),
            (st.step[1] / self.spec.step_max).clamp(-1.0, 1.0),
            info_db(st.info[0]),
            info_db(st.info[2]),
            corr.clamp(-1.0, 1.0),
            st.rms_v / 0.01,
            (s.voltage_v - v_pred) / 0.01,
            (s.voltage_v - 3.6) / 0.5,
            (v_pred - 3.6) / 0.5,
            s.current_a / 4.0,
            match s.request {
                Request::PowerW(w) => w / 16.0,
                Request::CurrentA(a) => a / 4.0,
                Request::Rest | Request::Unknown => 0.0,
            },
            (xn_now - p.xn_min) / (p.xn_max - p.xn_min),
            drawn_c / 5000.0,
            (1.0 + elapsed.max(0.0) / 100.0).ln() / 100f64.ln(),
            (1.0 + self.window.readings()).ln() / 8.0,
            self.interval_s / 20.0,
            (cell.track.t_k - 298.15) / 20.0,
            if self.loaded { 1.0 } else { 0.0 },
            (1.0 + self.readings as f64).ln() / 8.0,
            cell.xn0 / p.xn_max,
        ];
        for (o, v) in out[..OBS_DIM].iter_mut().zip(f) {
            *o = v as f32;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use bcal_common::dataset::Split;
    use bcal_common::measured::scenario::{draw_spec, simulate, Episode, EpisodeSpec, ScenarioConfig};
    use rand::SeedableRng;

    /// One simulated training discharge under a piecewise load (seed 5): its plan and its readings.
    fn piecewise_discharge() -> (EpisodeSpec, Episode) {
        let cfg = ScenarioConfig {
            load_kinds: vec![bcal_common::measured::scenario::LoadKind::Piecewise],
            ..Default::default()
        };
        let mut rng = rand::rngs::SmallRng::seed_from_u64(5);
        let spec = draw_spec(&cfg, Split::Train, &mut rng);
        let ep = simulate(&cfg, &spec).unwrap();
        (spec, ep)
    }

    /// Fed a simulated discharge and moved along its own fit step, the calibrator's estimate converges near
    /// the hidden truth, its observation stays finite and its cost falls to about the sensor noise.
    #[test]
    fn following_the_fit_step_finds_the_hidden_parameters() {
        let (spec, ep) = piecewise_discharge();
        let ts = TrackerSpec { action: ActionMode::Absolute, ..TrackerSpec::default() };
        let mut tr = Tracker::new(&ts);
        let mut obs = [0f32; OBS_DIM];
        let mut costs = Vec::new();
        for s in &ep.samples {
            tr.ingest(s);
            tr.observe(&mut obs);
            assert!(obs.iter().all(|v| v.is_finite()), "{obs:?}");
            let step = tr.stats().step;
            let a = [(step[0] / ts.step_max) as f32, (step[1] / ts.step_max) as f32];
            tr.apply_action(&a);
            costs.push(tr.cost());
        }
        let est = tr.estimate();
        let t = spec.truth;
        assert!((est.r_o_ohm - t.r_o_ohm).abs() < 0.01, "Ro {} vs {}", est.r_o_ohm, t.r_o_ohm);
        assert!((est.q_mobile_c - t.q_mobile_c).abs() < 300.0, "qMobile {} vs {}", est.q_mobile_c, t.q_mobile_c);
        let late = costs[costs.len() / 2..].iter().sum::<f64>() / (costs.len() - costs.len() / 2) as f64;
        // 3 mV of sensor noise costs ln(1 + 3) = 1.39; a wrong estimate's tens of mV cost 3 and more.
        assert!(late < 2.0, "late cost {late}");
        assert!(tr.interval().is_some());
    }

    /// A discharge whose first reading is already under load (a stream joined mid-discharge): the rest
    /// voltage the start is read from is a loaded one, about 0.1 V low. Held, that start's error stays in
    /// qMobile to the end; fitted with its uncertainty, the fit finds the start and qMobile comes back.
    #[test]
    fn a_discharge_joined_under_load_finds_its_start_when_the_start_is_fitted() {
        let (spec, ep) = piecewise_discharge();
        let first_loaded = ep.samples.iter().position(|s| s.current_a > 0.5).unwrap();
        let run = |fit_start: bool| {
            let mut fit =
                crate::tracker_based::WindowFitCalibrator::new(&TrackerSpec { fit_start, ..Default::default() });
            for s in &ep.samples[first_loaded..] {
                crate::Calibrator::step(&mut fit, s);
            }
            (crate::Calibrator::estimate(&fit).q_mobile_c - spec.truth.q_mobile_c).abs()
        };
        let (held, fitted) = (run(false), run(true));
        assert!(held > 100.0, "a loaded first reading makes a held start wrong: qMobile off by {held} C");
        assert!(fitted < 0.5 * held, "fitted start: qMobile off by {fitted} C, held {held} C");
    }
}
