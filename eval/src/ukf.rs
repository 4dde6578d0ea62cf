//! The unscented Kalman filter baseline (paper Section 4.3.1), made as strong as it honestly can be.
//!
//! Hidden state z: the calibrated parameters (one or two), each scaled to [0, 1] by the Table-1 ranges
//! (qMobile 4000..7000 C, Ro 0.1..0.2 ohm), following a random walk (z_{t+1} = z_t + w, w ~ N(0, Q)).
//! Measurement: the next battery state x_{t+1} (seven numbers), each divided by its training standard
//! deviation ([`ObsScales`]) so one scalar R fits all seven. Prediction: one battery-model step from the
//! *measured* state x_t under each sigma point's parameters (the same x_hat as the RL evaluation, so the
//! filter and the policy see the same information). Merwe scaled sigma points (Wan & van der Merwe 2000).
//! The filter restarts at every trajectory, as in the paper. Q, R, P0 and (alpha, beta, kappa) are chosen by
//! [`tune`] on validation trajectories only.
//!
//! Failure handling: a failed Cholesky of the sigma-point covariance is retried with growing diagonal
//! jitter, then the covariance is reset to P0; a failed Cholesky of the innovation covariance (or a
//! non-finite predicted measurement) skips that update. Both are counted in [`UkfCounters`], never hidden.
//! This module never prints.

use bcal_common::battery::{BatteryModel, Degradation, Load};
use bcal_common::dataset::Trajectory;
use bcal_common::math::{electro, StateVec, N_STATE};
use bcal_common::mdp::{model_state_at, state_at, ActionMap, Calibrated, ObsScales};
use bcal_common::nrmse::Param;
use nalgebra::{Cholesky, SMatrix, SVector};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

/// Largest number of sigma points (2 N + 1 with N = 2 parameters).
const MAX_SIGMA: usize = 5;
/// Initial mean of every normalised parameter: the middle of the data range, which is the mean of the
/// training grid (the only prior a filter may take from the data).
pub const PRIOR_MEAN: f64 = 0.5;

/// Every setting of the filter. The defaults lie in the best region of [`tune`]'s search on all three
/// experiments (the known-parameter tests use them); the evaluation always tunes its own on the validation
/// split.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct UkfSettings {
    /// Random-walk standard deviation of each normalised parameter per step (1 = the whole data range).
    pub q_std: f64,
    /// Measurement noise standard deviation, in units of each state's training standard deviation.
    pub r_std: f64,
    /// Initial standard deviation of each normalised parameter.
    pub p0_std: f64,
    /// Merwe spread of the sigma points around the mean.
    pub alpha: f64,
    /// Merwe prior-knowledge weight (2 is optimal for Gaussians).
    pub beta: f64,
    /// Merwe secondary scaling.
    pub kappa: f64,
}

impl Default for UkfSettings {
    fn default() -> Self {
        Self { q_std: 1e-4, r_std: 1e-5, p0_std: 0.5, alpha: 0.5, beta: 2.0, kappa: 0.0 }
    }
}

pub use bcal_calib::rescue::{sqrt_or_rescue, UkfCounters};

/// Measurement vector type: the normalised next state.
type Meas = StateVec;
type MeasCov = SMatrix<f64, N_STATE, N_STATE>;

/// A Merwe-scaled UKF over `N` random-walk parameters with a seven-dimensional measurement.
#[derive(Clone, Debug)]
pub struct Ukf<const N: usize> {
    settings: UkfSettings,
    z: SVector<f64, N>,
    p: SMatrix<f64, N, N>,
    p0: SMatrix<f64, N, N>,
    q: SMatrix<f64, N, N>,
    r: MeasCov,
    /// sqrt(N + lambda): sigma points sit at z +- gamma * columns of chol(P).
    gamma: f64,
    wm0: f64,
    wc0: f64,
    wi: f64,
    /// Lower and upper bound of each normalised parameter (the calibrators' shared output range).
    lo: SVector<f64, N>,
    hi: SVector<f64, N>,
    pub counters: UkfCounters,
}

impl<const N: usize> Ukf<N> {
    /// A filter at the prior, with the state clamped to `[lo, hi]` (normalised units).
    pub fn new(settings: UkfSettings, lo: SVector<f64, N>, hi: SVector<f64, N>) -> Self {
        let n = N as f64;
        let lambda = settings.alpha * settings.alpha * (n + settings.kappa) - n;
        let wm0 = lambda / (n + lambda);
        let p0 = SMatrix::<f64, N, N>::identity() * settings.p0_std.powi(2);
        Self {
            settings,
            z: SVector::repeat(PRIOR_MEAN),
            p: p0,
            p0,
            q: SMatrix::identity() * settings.q_std.powi(2),
            r: MeasCov::identity() * settings.r_std.powi(2),
            gamma: (n + lambda).sqrt(),
            wm0,
            wc0: wm0 + 1.0 - settings.alpha * settings.alpha + settings.beta,
            wi: 0.5 / (n + lambda),
            lo,
            hi,
            counters: UkfCounters::default(),
        }
    }

    /// Back to the prior (a new trajectory); counters are kept.
    pub fn reset(&mut self) {
        self.z = SVector::repeat(PRIOR_MEAN);
        self.p = self.p0;
    }

    pub fn estimate(&self) -> SVector<f64, N> {
        self.z
    }

    pub fn covariance(&self) -> SMatrix<f64, N, N> {
        self.p
    }

    pub fn settings(&self) -> &UkfSettings {
        &self.settings
    }

    fn sqrt_p(&mut self) -> Option<SMatrix<f64, N, N>> {
        sqrt_or_rescue(&mut self.p, &self.p0, 1e-12, &mut self.counters)
    }

    /// One predict-update cycle: random-walk prediction, sigma points through `h` (parameters -> predicted
    /// normalised measurement), update with the measurement `y`.
    pub fn step(&mut self, mut h: impl FnMut(&SVector<f64, N>) -> Meas, y: &Meas) {
        // Predict: z_{t+1|t} = z_t, P_{t+1|t} = P_t + Q (Eq. 9's constant parameters plus the random walk).
        self.p += self.q;
        let Some(l) = self.sqrt_p() else {
            self.counters.skipped_updates += 1;
            return;
        };
        let mut sig = [SVector::<f64, N>::zeros(); MAX_SIGMA];
        let mut ys = [Meas::zeros(); MAX_SIGMA];
        let n_sig = 2 * N + 1;
        sig[0] = self.z;
        for j in 0..N {
            let col = l.column(j) * self.gamma;
            sig[1 + j] = self.z + col;
            sig[1 + N + j] = self.z - col;
        }
        for i in 0..n_sig {
            // The model is evaluated inside the valid range only; the sigma point keeps its position.
            let clamped = sig[i].zip_zip_map(&self.lo, &self.hi, |v, lo, hi| v.clamp(lo, hi));
            ys[i] = h(&clamped);
            if ys[i].iter().any(|v| !v.is_finite()) {
                self.counters.skipped_updates += 1;
                return;
            }
        }
        let y_mean = ys[0] * self.wm0 + ys[1..n_sig].iter().fold(Meas::zeros(), |acc, v| acc + v) * self.wi;
        let mut s = self.r;
        let mut pzy = SMatrix::<f64, N, N_STATE>::zeros();
        for i in 0..n_sig {
            let w = if i == 0 { self.wc0 } else { self.wi };
            let dy = ys[i] - y_mean;
            let dz = sig[i] - self.z;
            s += dy * dy.transpose() * w;
            pzy += dz * dy.transpose() * w;
        }
        let Some(s_chol) = Cholesky::new(s) else {
            self.counters.skipped_updates += 1;
            return;
        };
        // K = Pzy S^-1, computed as (S^-1 Pzy^T)^T with the Cholesky factor (S is symmetric).
        let k = s_chol.solve(&pzy.transpose()).transpose();
        self.z += k * (y - y_mean);
        self.p -= k * s * k.transpose();
        self.p = (self.p + self.p.transpose()) * 0.5;
        self.z = self.z.zip_zip_map(&self.lo, &self.hi, |v, lo, hi| v.clamp(lo, hi));
    }
}

/// Maps between degradations and the normalised parameters the filter tracks.
#[derive(Clone, Debug)]
pub struct ParamScale {
    pub actions: ActionMap,
}

impl ParamScale {
    fn norm_q(q: f64) -> f64 {
        Param::QMobile.normalise(q)
    }
    fn norm_r(r: f64) -> f64 {
        Param::ROhm.normalise(r)
    }
    fn q_of(z: f64) -> f64 {
        Param::QMobile.denormalise(z)
    }
    fn r_of(z: f64) -> f64 {
        Param::ROhm.denormalise(z)
    }

    /// The degradation of normalised parameters `z` (uncalibrated ones at the experiment's fixed values).
    pub fn degradation(&self, z: &[f64]) -> Degradation {
        let mut d = self.actions.fixed;
        match self.actions.calibrated {
            Calibrated::QMobile => d.q_mobile_c = Self::q_of(z[0]),
            Calibrated::ROhm => d.r_o_ohm = Self::r_of(z[0]),
            Calibrated::Both => {
                d.q_mobile_c = Self::q_of(z[0]);
                d.r_o_ohm = Self::r_of(z[1]);
            }
        }
        d
    }

    /// Normalised bounds of the calibrators' output range (the action map's ranges).
    pub fn bounds(&self) -> ([f64; 2], [f64; 2]) {
        let [ql, qh] = self.actions.q_mobile_range_c;
        let [rl, rh] = self.actions.r_o_range_ohm;
        let q = [Self::norm_q(ql), Self::norm_q(qh)];
        let r = [Self::norm_r(rl), Self::norm_r(rh)];
        match self.actions.calibrated {
            Calibrated::QMobile => ([q[0], 0.0], [q[1], 0.0]),
            Calibrated::ROhm => ([r[0], 0.0], [r[1], 0.0]),
            Calibrated::Both => ([q[0], r[0]], [q[1], r[1]]),
        }
    }
}

/// The UKF as a calibrator along whole trajectories.
#[derive(Clone, Debug)]
pub struct UkfCalibrator {
    pub settings: UkfSettings,
    pub scale: ParamScale,
    /// Per-state divisor of the measurement (the training standard deviation).
    pub state_std: [f64; N_STATE],
    pub dt_s: f64,
}

impl UkfCalibrator {
    pub fn new(settings: UkfSettings, actions: &ActionMap, scales: &ObsScales, dt_s: f64) -> Self {
        Self { settings, scale: ParamScale { actions: actions.clone() }, state_std: scales.state_std, dt_s }
    }

    /// Runs the filter from its prior along `traj`; `on_step(t, estimate)` for t = 0 .. len - 2, where the
    /// estimate at t has seen x_{t+1} (the same information the policy's action a_t has).
    pub fn run(
        &self,
        model: &BatteryModel,
        traj: &Trajectory,
        on_step: impl FnMut(usize, &Degradation),
    ) -> UkfCounters {
        match self.scale.actions.dim() {
            1 => self.run_n::<1>(model, traj, on_step),
            _ => self.run_n::<2>(model, traj, on_step),
        }
    }

    fn run_n<const N: usize>(
        &self,
        model: &BatteryModel,
        traj: &Trajectory,
        mut on_step: impl FnMut(usize, &Degradation),
    ) -> UkfCounters {
        let (lo, hi) = self.scale.bounds();
        let mut ukf = Ukf::<N>::new(self.settings, SVector::from_fn(|k, _| lo[k]), SVector::from_fn(|k, _| hi[k]));
        let inv_std = StateVec::from_fn(|k, _| 1.0 / self.state_std[k]);
        let load = Load::PowerW(traj.load_w);
        for t in 0..traj.len().saturating_sub(1) {
            let x_t = model_state_at(model, traj, t);
            let y = state_at(traj, t + 1).component_mul(&inv_std);
            ukf.step(
                |z| {
                    let d = self.scale.degradation(z.as_slice());
                    let (next, _) = model.step(&x_t, load, self.dt_s, &d);
                    electro(&next).component_mul(&inv_std)
                },
                &y,
            );
            on_step(t, &self.scale.degradation(ukf.estimate().as_slice()));
        }
        ukf.counters
    }
}

/// The search space of [`tune`]: every combination is tried.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct UkfGrid {
    pub q_std: Vec<f64>,
    pub r_std: Vec<f64>,
    pub p0_std: Vec<f64>,
    /// (alpha, beta, kappa) triples.
    pub sigma: Vec<(f64, f64, f64)>,
}

impl Default for UkfGrid {
    /// Decades around the scales that matter: Q from "parameters constant" to 0.1 % of the range per step, R
    /// from the f32 storage noise of the data (~1e-7 of a std) to 1 % of a std, P0 from a quarter to the
    /// whole range, and three sigma-point spreads (tight, medium, classic alpha = 1 with kappa = 3 - N).
    fn default() -> Self {
        Self {
            q_std: vec![0.0, 1e-5, 1e-4, 1e-3],
            r_std: vec![1e-7, 1e-6, 1e-5, 1e-4, 1e-3, 1e-2],
            p0_std: vec![0.25, 0.5, 1.0],
            sigma: vec![(1e-3, 2.0, 0.0), (0.5, 2.0, 0.0), (1.0, 2.0, -1.0)],
        }
    }
}

impl UkfGrid {
    /// A smaller grid for quick runs (the best region of the default grid on all three experiments).
    pub fn quick() -> Self {
        Self {
            q_std: vec![0.0, 1e-4],
            r_std: vec![1e-6, 1e-5, 1e-4],
            p0_std: vec![0.5],
            sigma: vec![(0.5, 2.0, 0.0), (1.0, 2.0, -1.0)],
        }
    }

    pub fn candidates(&self, n_params: usize) -> Vec<UkfSettings> {
        let mut v = Vec::new();
        for &q_std in &self.q_std {
            for &r_std in &self.r_std {
                for &p0_std in &self.p0_std {
                    for &(alpha, beta, kappa) in &self.sigma {
                        // kappa = -1 in the grid stands for the classic 3 - N.
                        let kappa = if kappa < 0.0 { 3.0 - n_params as f64 } else { kappa };
                        v.push(UkfSettings { q_std, r_std, p0_std, alpha, beta, kappa });
                    }
                }
            }
        }
        v
    }
}

/// One tried setting and its validation error.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TuneRow {
    pub settings: UkfSettings,
    /// Per-step normalised RMSE on the tuning (validation) trajectories, %, root of the mean over the
    /// calibrated parameters.
    pub validation_nrmse_pct: f64,
}

/// The result of the search.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TuneResult {
    pub best: UkfSettings,
    pub best_validation_nrmse_pct: f64,
    pub candidates: usize,
    pub tuning_trajectories: usize,
    pub tuning_steps: usize,
    /// The five best settings, best first.
    pub top: Vec<TuneRow>,
    pub grid: UkfGrid,
}

/// Squared normalised error of the calibrated parameters, summed over them, and their count.
fn sq_err(actions: &ActionMap, est: &Degradation, truth: &Degradation) -> (f64, usize) {
    let eq = ParamScale::norm_q(est.q_mobile_c) - ParamScale::norm_q(truth.q_mobile_c);
    let er = ParamScale::norm_r(est.r_o_ohm) - ParamScale::norm_r(truth.r_o_ohm);
    match actions.calibrated {
        Calibrated::QMobile => (eq * eq, 1),
        Calibrated::ROhm => (er * er, 1),
        Calibrated::Both => (eq * eq + er * er, 2),
    }
}

/// Grid search of the filter's settings on validation trajectories (never test ones), on all cores.
pub fn tune(
    grid: &UkfGrid,
    validation: &[&Trajectory],
    model: &BatteryModel,
    actions: &ActionMap,
    scales: &ObsScales,
    dt_s: f64,
) -> TuneResult {
    let cands = grid.candidates(actions.dim());
    let steps: usize = validation.iter().map(|t| t.len().saturating_sub(1)).sum();
    let mut rows: Vec<TuneRow> = cands
        .par_iter()
        .map(|s| {
            let cal = UkfCalibrator::new(*s, actions, scales, dt_s);
            let (mut sum, mut n) = (0.0, 0usize);
            for traj in validation {
                cal.run(model, traj, |_, est| {
                    let (e, k) = sq_err(actions, est, &traj.degradation);
                    sum += e;
                    n += k;
                });
            }
            let pct = 100.0 * (sum / n.max(1) as f64).sqrt();
            TuneRow { settings: *s, validation_nrmse_pct: if pct.is_finite() { pct } else { f64::INFINITY } }
        })
        .collect();
    rows.sort_by(|a, b| a.validation_nrmse_pct.total_cmp(&b.validation_nrmse_pct));
    TuneResult {
        best: rows[0].settings,
        best_validation_nrmse_pct: rows[0].validation_nrmse_pct,
        candidates: rows.len(),
        tuning_trajectories: validation.len(),
        tuning_steps: steps,
        top: rows.iter().take(5).cloned().collect(),
        grid: grid.clone(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Vector2;

    /// A linear problem with a known answer: the filter must converge to it.
    #[test]
    fn linear_measurement_converges_to_the_truth() {
        let s = UkfSettings { q_std: 0.0, r_std: 1e-3, p0_std: 1.0, alpha: 0.5, beta: 2.0, kappa: 0.0 };
        let mut ukf = Ukf::<2>::new(s, Vector2::repeat(-5.0), Vector2::repeat(5.0));
        let truth = Vector2::new(0.3, 0.8);
        let h = |z: &Vector2<f64>| Meas::from_fn(|k, _| (k as f64 + 1.0) * z[0] - 0.5 * k as f64 * z[1]);
        for _ in 0..20 {
            ukf.step(h, &h(&truth));
        }
        assert!((ukf.estimate() - truth).norm() < 1e-6, "{}", ukf.estimate());
        assert_eq!(ukf.counters, UkfCounters::default());
    }

    #[test]
    fn non_finite_prediction_skips_the_update_and_counts_it() {
        let mut ukf = Ukf::<1>::new(UkfSettings::default(), SVector::repeat(0.0), SVector::repeat(1.0));
        ukf.step(|_| Meas::repeat(f64::NAN), &Meas::zeros());
        assert_eq!(ukf.counters.skipped_updates, 1);
        assert_eq!(ukf.estimate()[0], PRIOR_MEAN);
    }

    #[test]
    fn broken_covariance_is_rescued_and_counted() {
        let mut ukf = Ukf::<2>::new(UkfSettings::default(), Vector2::repeat(0.0), Vector2::repeat(1.0));
        // An indefinite covariance (as rounding could leave after many updates).
        ukf.p = SMatrix::<f64, 2, 2>::new(1.0, 2.0, 2.0, 1.0);
        ukf.step(|z| Meas::repeat(z[0] + z[1]), &Meas::repeat(1.0));
        assert_eq!(ukf.counters.covariance_resets, 1);
        assert!(ukf.estimate().iter().all(|v| v.is_finite()));
    }

    use bcal_common::config::EnvConfig;
    use bcal_common::dataset::{generate, simulate_trajectory, Dataset, Experiment, ExperimentDef, Grid, Split};
    use bcal_common::mdp::MdpSpec;

    /// A small data set of `experiment`'s kind (for the observation scales) and its MDP.
    fn small(experiment: Experiment) -> (Dataset, MdpSpec) {
        let paper = experiment.definition();
        let def = ExperimentDef {
            q_mobile_c: if paper.q_mobile_c.n > 1 { Grid { n: 3, ..paper.q_mobile_c } } else { paper.q_mobile_c },
            r_o_ohm: if paper.r_o_ohm.n > 1 { Grid { n: 3, ..paper.r_o_ohm } } else { paper.r_o_ohm },
            ..paper
        };
        let ds = generate(&def, &BatteryModel::default(), Split::Train).unwrap();
        let spec = MdpSpec::new(experiment, &EnvConfig::default(), &ds);
        (ds, spec)
    }

    /// The UKF recovers known parameters to within 1 % on noise-free trajectories of every experiment.
    #[test]
    fn ukf_recovers_known_parameters_within_1_percent() {
        let model = BatteryModel::default();
        for experiment in Experiment::ALL {
            let (_, spec) = small(experiment);
            let cal = UkfCalibrator::new(UkfSettings::default(), &spec.actions, &spec.scales, 1.0);
            let truths: Vec<(f64, f64, f64)> = match experiment {
                Experiment::SingleQ => vec![(4321.0, 0.117215, 14.0), (6789.0, 0.117215, 16.0)],
                Experiment::SingleR => vec![(7600.0, 0.1037, 14.5), (7600.0, 0.1913, 15.5)],
                Experiment::Multi => vec![(4450.0, 0.1825, 14.0), (6620.0, 0.1125, 16.0)],
            };
            for (q, r, load) in truths {
                let truth = Degradation { q_mobile_c: q, r_o_ohm: r };
                let traj = simulate_trajectory(&model, &truth, load, 1.0, 100_000).unwrap();
                let mut est = Vec::new();
                let counters = cal.run(&model, &traj, |_, d| est.push(*d));
                assert_eq!(est.len(), traj.len() - 1);
                // From a tenth of the discharge on, every step's estimate is within 1 % of the truth.
                let worst = est[est.len() / 10..]
                    .iter()
                    .map(|d| ((d.q_mobile_c - q) / q).abs().max(((d.r_o_ohm - r) / r).abs()))
                    .fold(0.0, f64::max);
                assert!(worst < 0.01, "{experiment} q {q} r {r}: worst relative error {worst:.4} ({counters:?})");
                let last = est.last().unwrap();
                eprintln!(
                    "{experiment} q {q} r {r}: worst {worst:.2e}, last {:.2} {:.5}, {counters:?}",
                    last.q_mobile_c, last.r_o_ohm
                );
            }
        }
    }
}
