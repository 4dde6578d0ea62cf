//! Learning on top of the best filter (issue 18): the correction policy observes the tuned joint UKF's
//! sufficient statistics and corrects it, so a zero action is the filter and training starts where the
//! best non-learned calibrator stands.
//!
//! [`Correction`] runs the filter one reading at a time and keeps what the policy sees beside it (recent
//! normalised innovations, the load, the time since the load last switched, the charge drawn so far);
//! [`Correction::observe`] writes the observation; [`Correction::apply_action`] turns an action in
//! [-1, 1]^4 into a shift of the reported estimate (in the filter's standard deviations; the filter keeps
//! its own mean) and the log-scales of the filter's parameter walk and measurement noise for the readings
//! to come (an adaptive filter whose rule is learned). [`CorrectionCalibrator`] is the deployed policy.
//! Everything here reads what a BMS has: voltage, current, temperature and time.

use crate::adaptive::CovarianceMatching;
use crate::joint_ukf::{JointUkf, NoiseScales};
use crate::{Calibrator, Interval};
use bcal_common::battery::Degradation;
use bcal_common::math::ModelState;
use bcal_common::measured::cellmodel::REST_CURRENT_A;
use bcal_common::measured::env::{CorrectionSpec, MeasuredSpec, CORRECTION_ACT_DIM, CORRECTION_OBS_DIM};
use bcal_common::measured::scenario::Sample;
use bcal_common::measured::tracker::{JointUkfSettings, TrackerSpec};
use bcal_common::policy::{PolicyNet, Scratch};

/// A change of the measured current between readings larger than this is a load switch, A.
pub const SWITCH_A: f64 = 0.2;
/// Readings over which the fast and slow innovation averages forget (exponential weights 1/n).
const FAST_READINGS: f64 = 8.0;
const SLOW_READINGS: f64 = 64.0;

/// The filter, the features beside it and the correction in force.
#[derive(Clone, Debug)]
pub struct Correction {
    ukf: JointUkf,
    /// The covariance-matching rule under the correction (`CorrectionSpec::adaptive`): it sets the noise.
    matching: Option<CovarianceMatching>,
    spec: CorrectionSpec,
    /// The tuned parameter walk's variance, z^2/s, and the one the action scales (the tuned one, or the
    /// floor when that is zero).
    tuned_walk_var: f64,
    walk_var_ref: f64,
    /// The action's shift of the reported estimate, in [-1, 1] of its largest shift.
    shift: [f64; 2],
    /// The last action (what the policy set; it sees it again).
    last_action: [f64; CORRECTION_ACT_DIM],
    last: Option<Sample>,
    first_t_s: f64,
    last_switch_t_s: f64,
    drawn_c: f64,
    loaded: bool,
    innovation_fast: f64,
    innovation_slow: f64,
    nis_slow: f64,
    readings: u64,
    /// The first reading's voltage (a cell at rest: its open-circuit voltage), V.
    rest_v: f64,
    /// Sum and count of the normalised innovations under load (their mean says how the model's shape
    /// departs from the cell's over the whole discharge so far).
    loaded_innovation_sum: f64,
    loaded_updates: f64,
}

impl Correction {
    /// The tuned filter `ukf` on the calibrator `tracker` (model, ranges, prior), corrected as `spec` says.
    pub fn new(tracker: &TrackerSpec, ukf: JointUkfSettings, spec: &CorrectionSpec) -> Self {
        let tuned_walk_var = ukf.param_walk_per_sqrt_s.powi(2);
        Self {
            walk_var_ref: tuned_walk_var.max(spec.walk_floor_per_sqrt_s.powi(2)),
            tuned_walk_var,
            matching: spec.adaptive.map(|rule| CovarianceMatching::new(rule, &ukf)),
            ukf: JointUkf::new(ukf, tracker),
            spec: spec.clone(),
            shift: [0.0; 2],
            last_action: [0.0; CORRECTION_ACT_DIM],
            last: None,
            first_t_s: 0.0,
            last_switch_t_s: 0.0,
            drawn_c: 0.0,
            loaded: false,
            innovation_fast: 0.0,
            innovation_slow: 0.0,
            nis_slow: 1.0,
            readings: 0,
            rest_v: 0.0,
            loaded_innovation_sum: 0.0,
            loaded_updates: 0.0,
        }
    }

    /// The correction of a measured-only task (its tuned filter and correction settings).
    pub fn of_task(spec: &MeasuredSpec) -> Self {
        Self::new(&spec.tracker, spec.ukf_settings(), &spec.correction)
    }

    pub fn ukf(&self) -> &JointUkf {
        &self.ukf
    }

    /// Takes one reading: the filter steps under the noise the last action set, the features follow.
    pub fn ingest(&mut self, s: &Sample) {
        self.ukf.step(s);
        if let Some(m) = &mut self.matching {
            m.after_step(&mut self.ukf);
        }
        self.readings += 1;
        match self.last {
            None => {
                self.first_t_s = s.t_s;
                self.last_switch_t_s = s.t_s;
                self.rest_v = s.voltage_v;
            }
            Some(p) => {
                // Charge drawn: the measured current held from the previous reading (as the filter drives).
                self.drawn_c += p.current_a * (s.t_s - p.t_s).max(0.0);
                let on = |x: &Sample| x.current_a.abs() >= REST_CURRENT_A;
                if (s.current_a - p.current_a).abs() > SWITCH_A || on(&p) != on(s) {
                    self.last_switch_t_s = s.t_s;
                }
            }
        }
        self.loaded |= s.current_a.abs() >= REST_CURRENT_A;
        if let Some(u) = self.ukf.last_update() {
            let nu = u.normalised().clamp(-10.0, 10.0);
            self.innovation_fast += (nu - self.innovation_fast) / FAST_READINGS.min(self.readings as f64);
            self.innovation_slow += (nu - self.innovation_slow) / SLOW_READINGS.min(self.readings as f64);
            self.nis_slow += (nu * nu - self.nis_slow) / SLOW_READINGS.min(self.readings as f64);
            if s.current_a.abs() >= REST_CURRENT_A {
                self.loaded_innovation_sum += nu;
                self.loaded_updates += 1.0;
            }
        }
        self.last = Some(*s);
    }

    /// The filter's standard deviations of zq and zr.
    fn sd_z(&self) -> [f64; 2] {
        let c = self.ukf.param_cov_z();
        [c[0].sqrt(), c[2].sqrt()]
    }

    /// The observation after the latest reading, written into `out[..CORRECTION_OBS_DIM]`.
    pub fn observe(&self, out: &mut [f32]) {
        let out = &mut out[..CORRECTION_OBS_DIM];
        let Some(s) = self.last else {
            out.fill(0.0);
            return;
        };
        let z = self.ukf.mean_z();
        let c = self.ukf.param_cov_z();
        let sd = [c[0].sqrt(), c[2].sqrt()];
        let corr = c[1] / (sd[0] * sd[1]).max(1e-30);
        // Standard deviations from 1e-4 to 1 of the range onto [-1, 1].
        let sd_feature = |v: f64| (v.max(1e-6).log10() + 2.0) / 2.0;
        let (nu_last, nu_v) = self.ukf.last_update().map_or((0.0, 0.0), |u| (u.normalised(), u.innovation_v));
        let p = self.ukf.model_params();
        let xn = (self.ukf.xn() - p.xn_min) / (p.xn_max - p.xn_min);
        let [vo, vsn, vsp] = self.ukf.overpotentials_v();
        let f = [
            2.0 * z[0] - 1.0,
            2.0 * z[1] - 1.0,
            sd_feature(sd[0]),
            sd_feature(sd[1]),
            corr.clamp(-1.0, 1.0),
            (nu_last / 3.0).clamp(-3.0, 3.0),
            self.innovation_fast / 2.0,
            self.innovation_slow / 2.0,
            self.nis_slow.max(1e-3).log10() / 2.0,
            (nu_v / 0.01).clamp(-5.0, 5.0),
            s.current_a / 4.0,
            (s.voltage_v - 3.6) / 0.5,
            (1.0 + (s.t_s - self.last_switch_t_s).max(0.0) / 10.0).ln() / 1000f64.ln(),
            self.drawn_c / 5000.0,
            xn,
            (1.0 + (s.t_s - self.first_t_s).max(0.0) / 100.0).ln() / 100f64.ln(),
            self.ukf.last_update().map_or(0.0, |u| u.dt_s) / 20.0,
            (s.temperature_k - 298.15) / 20.0,
            (vo + vsn + vsp) / 0.5,
            if self.loaded { 1.0 } else { 0.0 },
            self.last_action[2],
            self.last_action[3],
            (self.rest_v - 3.6) / 0.5,
            self.loaded_innovation_sum / self.loaded_updates.max(1.0) / 2.0,
        ];
        for (o, v) in out.iter_mut().zip(f) {
            *o = v as f32;
        }
    }

    /// Applies an action (each component clamped to [-1, 1]): the shift of the reported estimate now, the
    /// filter's noise for the readings to come.
    pub fn apply_action(&mut self, action: &[f32]) {
        let a: [f64; CORRECTION_ACT_DIM] =
            std::array::from_fn(|k| action.get(k).map_or(0.0, |v| f64::from(v.clamp(-1.0, 1.0))));
        self.last_action = a;
        // a |a|: fine control near zero, where a precisely known parameter (Ro within a fraction of a
        // percent) can only be nudged, and the whole reach at the ends, where model error needs it.
        self.shift = [a[0] * a[0].abs(), a[1] * a[1].abs()];
        if self.matching.is_some() {
            // The rule owns the filter's noise (the config refuses noise actions beside it).
            return;
        }
        // Zero action is the tuned filter exactly (also when its tuned walk is zero).
        let walk = if a[2] == 0.0 {
            self.tuned_walk_var
        } else {
            self.walk_var_ref * 10f64.powf(a[2] * self.spec.walk_decades)
        };
        let meas_var = 10f64.powf(a[3] * self.spec.meas_decades);
        self.ukf.set_noise_scales(NoiseScales { param_walk_var_per_s: Some([walk; 2]), meas_var });
    }

    /// The corrected estimate: the filter's mean shifted by the action (in units of its largest shift: the
    /// filter's standard deviations plus a floor).
    pub fn estimate(&self) -> Degradation {
        let z = self.ukf.mean_z();
        let sd = self.sd_z();
        let reach = |k: usize| self.spec.shift_max_sd * sd[k] + self.spec.shift_floor_z;
        self.ukf.spec().from_z([z[0] + self.shift[0] * reach(0), z[1] + self.shift[1] * reach(1)])
    }

    /// The 90 % interval around the corrected estimate: the filter's standard deviations times the
    /// validation-chosen scales.
    pub fn interval(&self) -> Option<Interval> {
        if !self.ukf.started() {
            return None;
        }
        let sd = self.sd_z();
        Some(crate::direct::interval_around(self.ukf.spec(), &self.estimate(), sd, self.spec.interval_scale))
    }

    /// The filter's model state given the corrected estimate (its conditional mean).
    pub fn state(&self) -> Option<ModelState> {
        self.ukf.started().then(|| self.ukf.state_given(&self.estimate()))
    }

    pub fn state_under(&self, d: &Degradation) -> Option<ModelState> {
        self.ukf.started().then(|| self.ukf.state_given(d))
    }
}

/// The correction policy as a calibrator: the filter reads, the policy's deterministic action corrects it.
/// With several policies (an ensemble: the same task trained from other seeds) the action is their mean,
/// which keeps what the seeds agree on and shrinks what one seed alone learned toward zero (the filter).
pub struct CorrectionCalibrator<'a> {
    core: Correction,
    nets: &'a [PolicyNet],
    scratch: Scratch,
    obs: [f32; CORRECTION_OBS_DIM],
}

impl<'a> CorrectionCalibrator<'a> {
    pub fn new(spec: &MeasuredSpec, net: &'a PolicyNet) -> Self {
        Self::ensemble(spec, std::slice::from_ref(net))
    }

    /// The mean action of `nets` (at least one, all trained on this task).
    pub fn ensemble(spec: &MeasuredSpec, nets: &'a [PolicyNet]) -> Self {
        assert!(!nets.is_empty(), "a correction policy needs at least one network");
        let widest = nets.iter().max_by_key(|n| n.layout().max_width()).expect("checked non-empty");
        Self {
            core: Correction::of_task(spec),
            scratch: Scratch::new(widest.layout()),
            nets,
            obs: [0.0; CORRECTION_OBS_DIM],
        }
    }

    pub fn core(&self) -> &Correction {
        &self.core
    }
}

impl Calibrator for CorrectionCalibrator<'_> {
    fn step(&mut self, s: &Sample) {
        self.core.ingest(s);
        self.core.observe(&mut self.obs);
        let mut sum = [0f32; CORRECTION_ACT_DIM];
        let mut a = [0f32; CORRECTION_ACT_DIM];
        let n = self.nets[0].layout().act_dim.min(CORRECTION_ACT_DIM);
        for net in self.nets {
            net.act_deterministic(&self.obs, &mut self.scratch, &mut a[..n]);
            for (t, x) in sum.iter_mut().zip(&a[..n]) {
                *t += x;
            }
        }
        let k = self.nets.len() as f32;
        for t in &mut sum[..n] {
            *t /= k;
        }
        self.core.apply_action(&sum[..n]);
    }
    fn estimate(&self) -> Degradation {
        self.core.estimate()
    }
    fn interval(&self) -> Option<Interval> {
        self.core.interval()
    }
    fn state(&self) -> Option<ModelState> {
        self.core.state()
    }
    fn state_under(&self, d: &Degradation) -> Option<ModelState> {
        self.core.state_under(d)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use bcal_common::dataset::Split;
    use bcal_common::measured::scenario::episode_set;
    use bcal_common::policy::PolicyLayout;

    /// A network whose deterministic action is tanh(`bias`) whatever it observes (all weights zero).
    fn constant_policy(spec: &MeasuredSpec, bias: &[f32]) -> PolicyNet {
        let layout = PolicyLayout { obs_dim: spec.obs_dim(), act_dim: spec.act_dim(), hidden: vec![8] };
        let mut params = vec![0f32; layout.n_params()];
        let linears = layout.linears();
        let hidden: usize = linears[..linears.len() - 2].iter().map(|(i, o)| i * o + o).sum();
        let (mean_in, mean_out) = linears[linears.len() - 2];
        let bias_at = hidden + mean_in * mean_out;
        params[bias_at..bias_at + bias.len()].copy_from_slice(bias);
        PolicyNet::from_flat(layout, params).unwrap()
    }

    /// An ensemble applies its members' mean action: with a zero member beside it, a policy's shift is
    /// halved, reading for reading, and the estimates differ from the filter's (else this proves nothing).
    #[test]
    fn an_ensemble_applies_the_mean_action() {
        let spec = MeasuredSpec::default();
        assert_eq!(spec.act_dim(), 2, "the default correction shifts qMobile and Ro only");
        let bias = [0.6f32, -0.4];
        let nets = [constant_policy(&spec, &bias), constant_policy(&spec, &[0.0, 0.0])];
        let half = [bias[0].tanh() / 2.0, bias[1].tanh() / 2.0];
        let ep = &episode_set(&spec.scenario, Split::Validation, 1).unwrap()[0];
        let mut ensemble = CorrectionCalibrator::ensemble(&spec, &nets);
        let mut by_hand = Correction::of_task(&spec);
        let mut filter = JointUkf::new(spec.ukf_settings(), &spec.tracker);
        let mut moved = 0;
        for s in &ep.samples {
            ensemble.step(s);
            by_hand.ingest(s);
            by_hand.apply_action(&half);
            filter.step(s);
            assert_eq!(ensemble.estimate(), by_hand.estimate());
            moved += usize::from(ensemble.estimate() != filter.estimate());
        }
        assert!(
            2 * moved > ep.samples.len(),
            "the mean action moved only {moved} of {} estimates off the filter's",
            ep.samples.len()
        );
    }
}
