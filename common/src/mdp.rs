//! The calibration MDP of the paper's Section 3.2.
//!
//! Observation s_t = [x_hat_t, x_{t+1}, u_{t+1}] (normalised), action = the calibrated degradation
//! parameters squashed to [-1, 1], transition x_hat_{t+1} = f(x_hat_t, a_t, u_{t+1}), cost
//! c_t = || x_hat_{t+1} - x_{t+1} || on the normalised state. The agent never sees the true parameters:
//! [`CalibrationEnv`] reads only states and loads of a trajectory, never its `degradation` field.
//!
//! Episodes are windows of `window_steps` steps of a training trajectory starting at a random step, with
//! x_hat set to the real state at the window start. Why windows: a whole discharge is 600-3000 steps and
//! its early steps would dominate the buffer; short windows from random starts cover every state of
//! charge evenly, and re-syncing x_hat at the start keeps the model's state close enough to the real one
//! that the one-step cost measures the parameters, not accumulated drift (the paper's code used 16).

use crate::battery::{BatteryModel, Degradation, Load};
use crate::config::EnvConfig;
use crate::dataset::{Dataset, Experiment, Trajectory};
use crate::math::{electro, idx, ModelState, StateVec, N_STATE};
use serde::{Deserialize, Serialize};

/// Which degradation parameters the agent calibrates; the others stay at the new-cell values.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum Calibrated {
    QMobile,
    ROhm,
    Both,
}

/// Affine map between actions in [-1, 1] and degradation parameters.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ActionMap {
    pub calibrated: Calibrated,
    pub q_mobile_range_c: [f64; 2],
    pub r_o_range_ohm: [f64; 2],
    /// Values of the parameters that are not calibrated (the experiment's fixed values).
    pub fixed: Degradation,
}

impl ActionMap {
    pub fn from_config(experiment: Experiment, env: &EnvConfig) -> Self {
        let calibrated = match experiment {
            Experiment::SingleQ => Calibrated::QMobile,
            Experiment::SingleR => Calibrated::ROhm,
            Experiment::Multi => Calibrated::Both,
        };
        let def = experiment.definition();
        let fixed = Degradation { q_mobile_c: def.q_mobile_c.start, r_o_ohm: def.r_o_ohm.start };
        Self { calibrated, q_mobile_range_c: env.q_mobile_range_c, r_o_range_ohm: env.r_o_range_ohm, fixed }
    }

    pub fn dim(&self) -> usize {
        match self.calibrated {
            Calibrated::Both => 2,
            _ => 1,
        }
    }

    /// Names of the action's parameters, in order.
    pub fn names(&self) -> &'static [&'static str] {
        match self.calibrated {
            Calibrated::QMobile => &["q_mobile"],
            Calibrated::ROhm => &["r_o"],
            Calibrated::Both => &["q_mobile", "r_o"],
        }
    }

    /// Degradation for an action in [-1, 1] (clamped there first).
    #[inline]
    pub fn to_degradation(&self, a: &[f32]) -> Degradation {
        let map = |v: f32, [lo, hi]: [f64; 2]| lo + (f64::from(v).clamp(-1.0, 1.0) + 1.0) * 0.5 * (hi - lo);
        let mut d = self.fixed;
        match self.calibrated {
            Calibrated::QMobile => d.q_mobile_c = map(a[0], self.q_mobile_range_c),
            Calibrated::ROhm => d.r_o_ohm = map(a[0], self.r_o_range_ohm),
            Calibrated::Both => {
                d.q_mobile_c = map(a[0], self.q_mobile_range_c);
                d.r_o_ohm = map(a[1], self.r_o_range_ohm);
            }
        }
        d
    }

    /// The action that yields `d` (inverse of [`Self::to_degradation`]); used by supervised baselines and tests.
    pub fn to_action(&self, d: &Degradation) -> [f32; 2] {
        let inv = |v: f64, [lo, hi]: [f64; 2]| ((v - lo) / (hi - lo) * 2.0 - 1.0) as f32;
        match self.calibrated {
            Calibrated::QMobile => [inv(d.q_mobile_c, self.q_mobile_range_c), 0.0],
            Calibrated::ROhm => [inv(d.r_o_ohm, self.r_o_range_ohm), 0.0],
            Calibrated::Both => [inv(d.q_mobile_c, self.q_mobile_range_c), inv(d.r_o_ohm, self.r_o_range_ohm)],
        }
    }
}

/// Fixed feature scales derived from the training set; they travel with the checkpoint.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ObsScales {
    /// Per-state mean over every step of every training trajectory.
    pub state_mean: [f64; N_STATE],
    /// Per-state standard deviation over the same steps (floored so no feature divides by ~0).
    pub state_std: [f64; N_STATE],
    pub load_mean_w: f64,
    pub load_std_w: f64,
    /// Mean and standard deviation of [`apparent_resistance_ohm`] over the training steps (absent in
    /// MDP files written before it existed; only [`ObservationKind::FullStateOhmic`] reads them).
    #[serde(default)]
    pub r_app_mean_ohm: f64,
    #[serde(default = "one")]
    pub r_app_std_ohm: f64,
}

fn one() -> f64 {
    1.0
}

impl ObsScales {
    /// Mean and standard deviation of each state and of the load over the training trajectories.
    pub fn from_train(ds: &Dataset) -> Self {
        let mut n = 0f64;
        let mut sum = [0f64; N_STATE];
        let mut sq = [0f64; N_STATE];
        let (mut ln, mut lsum, mut lsq) = (0f64, 0f64, 0f64);
        let (mut rsum, mut rsq) = (0f64, 0f64);
        for t in ds.train() {
            for (s, v) in t.states.iter().zip(&t.voltage_v) {
                let r = apparent_resistance_ohm(f64::from(s[idx::V_O]), *v, t.load_w);
                rsum += r;
                rsq += r * r;
                for k in 0..N_STATE {
                    let v = f64::from(s[k]);
                    sum[k] += v;
                    sq[k] += v * v;
                }
            }
            n += t.states.len() as f64;
            ln += 1.0;
            lsum += t.load_w;
            lsq += t.load_w * t.load_w;
        }
        let std = |s: f64, q: f64, n: f64| ((q / n - (s / n).powi(2)).max(0.0)).sqrt();
        let mut state_mean = [0.0; N_STATE];
        let mut state_std = [0.0; N_STATE];
        for k in 0..N_STATE {
            state_mean[k] = sum[k] / n;
            // Floor at 1e-6 of the mean magnitude (or 1e-9) so a constant feature stays finite.
            state_std[k] = std(sum[k], sq[k], n).max(state_mean[k].abs() * 1e-6).max(1e-9);
        }
        let load_std_w = std(lsum, lsq, ln).max(1e-3);
        Self {
            state_mean,
            state_std,
            load_mean_w: lsum / ln,
            load_std_w,
            r_app_mean_ohm: rsum / n,
            r_app_std_ohm: std(rsum, rsq, n).max(1e-6),
        }
    }

    #[inline]
    pub fn normalise_state(&self, x: &StateVec, out: &mut [f32]) {
        for k in 0..N_STATE {
            out[k] = ((x[k] - self.state_mean[k]) / self.state_std[k]) as f32;
        }
    }

    #[inline]
    pub fn normalise_load(&self, load_w: f64) -> f32 {
        ((load_w - self.load_mean_w) / self.load_std_w) as f32
    }

    /// The MDP cost: Euclidean norm of the state error, each state divided by its scale.
    #[inline]
    pub fn cost(&self, x_hat: &StateVec, x_real: &StateVec) -> f64 {
        let mut s = 0.0;
        for k in 0..N_STATE {
            let e = (x_hat[k] - x_real[k]) / self.state_std[k];
            s += e * e;
        }
        s.sqrt()
    }
}

/// How an observation is assembled: one small, replaceable piece.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub enum ObservationKind {
    /// The paper's [x_hat_t, x_{t+1}, u_{t+1}]: 7 + 7 + 1 features.
    FullState,
    /// The paper's features plus the cell's apparent ohmic resistance at t+1, Vo / i with i = P / V
    /// (what an engineer reads off a voltage step); it depends on the load far less than Vo itself, so the
    /// policy need not extrapolate a division to loads it never saw.
    #[default]
    FullStateOhmic,
}

impl ObservationKind {
    pub fn dim(self) -> usize {
        match self {
            ObservationKind::FullState => 2 * N_STATE + 1,
            ObservationKind::FullStateOhmic => 2 * N_STATE + 2,
        }
    }

    /// Writes the observation of x_hat_t against the measured row `row` (= t + 1) of `traj` into
    /// `out[..self.dim()]`.
    #[inline]
    pub fn build(self, scales: &ObsScales, x_hat: &StateVec, traj: &Trajectory, row: usize, out: &mut [f32]) {
        let x_next = state_at(traj, row);
        scales.normalise_state(x_hat, &mut out[0..N_STATE]);
        scales.normalise_state(&x_next, &mut out[N_STATE..2 * N_STATE]);
        out[2 * N_STATE] = scales.normalise_load(traj.load_w);
        if self == ObservationKind::FullStateOhmic {
            let r = apparent_resistance_ohm(x_next[idx::V_O], traj.voltage_v[row], traj.load_w);
            out[2 * N_STATE + 1] = ((r - scales.r_app_mean_ohm) / scales.r_app_std_ohm) as f32;
        }
    }
}

/// Vo / i with i = P / V: the ohmic overpotential per ampere, ohm.
#[inline]
pub fn apparent_resistance_ohm(vo_v: f64, voltage_v: f32, load_w: f64) -> f64 {
    vo_v * f64::from(voltage_v) / load_w
}

/// Everything that defines the MDP apart from the data; shared by actors, learner validation and evaluator.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct MdpSpec {
    pub observation: ObservationKind,
    pub actions: ActionMap,
    pub scales: ObsScales,
    pub window_steps: usize,
    pub dt_s: f64,
    /// Cost shaping: 0 gives the paper's cost c = e (the normalised tracking error); e0 > 0 gives
    /// c = ln(1 + e / e0). See [`MdpSpec::cost_of`].
    pub cost_log_e0: f64,
}

impl MdpSpec {
    pub fn new(experiment: Experiment, env: &EnvConfig, train: &Dataset) -> Self {
        Self {
            observation: env.observation,
            actions: ActionMap::from_config(experiment, env),
            scales: ObsScales::from_train(train),
            window_steps: env.window_steps,
            dt_s: train.def.dt_s,
            cost_log_e0: env.cost_log_e0,
        }
    }

    /// The RL cost of a tracking error e = || x_hat_{t+1} - x_{t+1} || (normalised state).
    ///
    /// Why a log option: e spans four decades (1e-4 near the true parameters, ~1 for a wild action), and
    /// the critic's regression error sits far above the 1e-3 differences that tell a 1 %-accurate action
    /// from a 4 % one. ln(1 + e / e0) is monotone in e and zero at e = 0, so it keeps the same minimiser
    /// (the true parameters) and a non-negative cost (the Lyapunov condition needs c >= 0), but turns
    /// relative improvements near the optimum into differences the critic can resolve.
    #[inline]
    pub fn cost_of(&self, tracking_error: f64) -> f64 {
        if self.cost_log_e0 > 0.0 {
            (tracking_error / self.cost_log_e0).ln_1p()
        } else {
            tracking_error
        }
    }

    pub fn obs_dim(&self) -> usize {
        self.observation.dim()
    }

    pub fn act_dim(&self) -> usize {
        self.actions.dim()
    }

    /// One MDP transition from model state `x_hat` under action `a`, towards the real `x_next` at load
    /// `load_w`: returns x_hat_{t+1} and the tracking error e (the paper's cost; see [`Self::cost_of`]).
    #[inline]
    pub fn transition(
        &self,
        model: &BatteryModel,
        x_hat: &ModelState,
        a: &[f32],
        load_w: f64,
        x_next: &StateVec,
    ) -> (ModelState, f64) {
        let d = self.actions.to_degradation(a);
        let (next, _) = model.step(x_hat, Load::PowerW(load_w), self.dt_s, &d);
        let cost = self.scales.cost(&electro(&next), x_next);
        (next, cost)
    }
}

/// The seven-state vector of row `t` of a trajectory, as f64.
#[inline]
pub fn state_at(traj: &Trajectory, t: usize) -> StateVec {
    StateVec::from_fn(|k, _| f64::from(traj.states[t][k]))
}

/// A full model state (isothermal) from row `t` of a trajectory.
#[inline]
pub fn model_state_at(model: &BatteryModel, traj: &Trajectory, t: usize) -> ModelState {
    let mut x = ModelState::zeros();
    for k in 0..N_STATE {
        x[k] = f64::from(traj.states[t][k]);
    }
    x[idx::T_B] = model.params.tb0_k;
    x
}

/// Small deterministic generator for window starts (splitmix64): actors need no other randomness source
/// for the environment, and a seed reproduces a run.
#[derive(Clone, Debug)]
pub struct SplitMix64(pub u64);

impl SplitMix64 {
    #[inline]
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e3779b97f4a7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58476d1ce4e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d049bb133111eb);
        z ^ (z >> 31)
    }

    /// Uniform in [0, n).
    #[inline]
    pub fn below(&mut self, n: usize) -> usize {
        (self.next_u64() % n as u64) as usize
    }

    /// Uniform in [0, 1).
    #[inline]
    pub fn unit_f64(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
    }

    /// Standard normal (Box-Muller).
    #[inline]
    pub fn normal(&mut self) -> f64 {
        let u1 = self.unit_f64().max(1e-300);
        let u2 = self.unit_f64();
        (-2.0 * u1.ln()).sqrt() * (2.0 * std::f64::consts::PI * u2).cos()
    }
}

/// One environment: a window of one training trajectory, stepped by a calibrator's actions.
#[derive(Clone, Debug)]
pub struct CalibrationEnv {
    traj: usize,
    /// Current step t (x_hat is the model's state at t; the observation looks at t + 1).
    t: usize,
    window_end: usize,
    x_hat: ModelState,
}

/// What one environment step returns.
#[derive(Clone, Copy, Debug)]
pub struct EnvStep {
    /// The RL cost (after the configured shaping).
    pub cost: f64,
    /// The normalised tracking error || x_hat_{t+1} - x_{t+1} ||.
    pub tracking_error: f64,
    /// True when the window (or the trajectory) ended: the next observation is still valid (a time limit,
    /// not a terminal state), and the environment has been reset.
    pub window_done: bool,
}

impl CalibrationEnv {
    /// A new environment at a random window of one of `trajectories` (indices into `ds`).
    pub fn new(
        spec: &MdpSpec,
        model: &BatteryModel,
        ds: &Dataset,
        trajectories: &[usize],
        rng: &mut SplitMix64,
    ) -> Self {
        let mut env = Self { traj: 0, t: 0, window_end: 0, x_hat: ModelState::zeros() };
        env.reset(spec, model, ds, trajectories, rng);
        env
    }

    /// Starts a new window: random trajectory, random start step, x_hat = the real state there.
    pub fn reset(
        &mut self,
        spec: &MdpSpec,
        model: &BatteryModel,
        ds: &Dataset,
        trajectories: &[usize],
        rng: &mut SplitMix64,
    ) {
        self.traj = trajectories[rng.below(trajectories.len())];
        let len = ds.trajectories[self.traj].len();
        // The observation at step t needs row t + 1, so a window can start at most at len - 2.
        let last_start = len.saturating_sub(2);
        self.t = rng.below(last_start + 1);
        self.window_end = (self.t + spec.window_steps).min(len - 1);
        self.x_hat = model_state_at(model, &ds.trajectories[self.traj], self.t);
    }

    /// The current observation, written into `out[..spec.obs_dim()]`.
    #[inline]
    pub fn observe(&self, spec: &MdpSpec, ds: &Dataset, out: &mut [f32]) {
        let traj = &ds.trajectories[self.traj];
        spec.observation.build(&spec.scales, &electro(&self.x_hat), traj, self.t + 1, out);
    }

    /// Applies action `a`: x_hat advances under the action's parameters; returns the cost. When the window
    /// ends, `next_obs` is the observation after the step (for the transition) and the env is reset.
    #[allow(clippy::too_many_arguments)]
    pub fn step(
        &mut self,
        spec: &MdpSpec,
        model: &BatteryModel,
        ds: &Dataset,
        trajectories: &[usize],
        a: &[f32],
        next_obs: &mut [f32],
        rng: &mut SplitMix64,
    ) -> EnvStep {
        let traj = &ds.trajectories[self.traj];
        let x_next = state_at(traj, self.t + 1);
        let (x_hat_next, error) = spec.transition(model, &self.x_hat, a, traj.load_w, &x_next);
        self.x_hat = x_hat_next;
        self.t += 1;
        // The next observation pairs x_hat_{t+1} with the real x_{t+2}; at the trajectory's last row there
        // is no x_{t+2}, so the last usable step is len - 2 and we pair with the last row instead.
        let look = (self.t + 1).min(traj.len() - 1);
        spec.observation.build(&spec.scales, &electro(&self.x_hat), traj, look, next_obs);
        let window_done = self.t >= self.window_end || self.t + 1 >= traj.len();
        if window_done {
            self.reset(spec, model, ds, trajectories, rng);
        }
        EnvStep { cost: spec.cost_of(error), tracking_error: error, window_done }
    }
}

/// Runs a calibrator along a whole trajectory (paper Fig. 1, part 2) and reports its estimate and the
/// one-step tracking error (unshaped) at every step t = 0 .. len - 2.
///
/// x_hat at evaluation time is the measured state x_t, re-synced every step: a deployed calibrator observes
/// the real battery at every step, and this is the distribution the policy was trained on (every window
/// starts from a measured state). Letting x_hat drift open-loop for thousands of steps would test a
/// situation training never showed, and would mix state-estimation error into the parameter error.
pub fn rollout_calibrator(
    spec: &MdpSpec,
    model: &BatteryModel,
    traj: &Trajectory,
    mut policy: impl FnMut(&[f32], &mut [f32]),
    mut on_step: impl FnMut(usize, &Degradation, f64),
) {
    let mut obs = [0f32; crate::wire::MAX_OBS];
    let mut action = [0f32; crate::wire::MAX_ACT];
    let (od, ad) = (spec.obs_dim(), spec.act_dim());
    for t in 0..traj.len().saturating_sub(1) {
        let x_hat = model_state_at(model, traj, t);
        let x_next = state_at(traj, t + 1);
        spec.observation.build(&spec.scales, &electro(&x_hat), traj, t + 1, &mut obs[..od]);
        policy(&obs[..od], &mut action[..ad]);
        let (_, cost) = spec.transition(model, &x_hat, &action[..ad], traj.load_w, &x_next);
        on_step(t, &spec.actions.to_degradation(&action[..ad]), cost);
    }
}

/// Mean one-step tracking error and Table-1 NRMSE (q_mobile %, r_o %) of a policy's deterministic action
/// along `trajectories` (indices into `ds`). Evaluation only: it reads the true parameters.
pub fn validate_policy(
    spec: &MdpSpec,
    model: &BatteryModel,
    ds: &Dataset,
    trajectories: &[usize],
    net: &crate::policy::PolicyNet,
) -> (f64, f64, f64) {
    let mut scratch = crate::policy::Scratch::new(net.layout());
    let mut acc = NrmseAccumulator::default();
    let (mut error_sum, mut n) = (0.0, 0u64);
    for &i in trajectories {
        let traj = &ds.trajectories[i];
        rollout_calibrator(
            spec,
            model,
            traj,
            |obs, a| net.act_deterministic(obs, &mut scratch, a),
            |_, estimate, error| {
                acc.add(estimate, &traj.degradation);
                error_sum += error;
                n += 1;
            },
        );
    }
    let (q, r) = acc.pct();
    (error_sum / n.max(1) as f64, q, r)
}

/// Normalised RMSE in % of the paper's Table 1: parameters scaled to [0, 1] by the data ranges
/// (qMobile 4000..7000 C, Ro 0.1..0.2 ohm).
pub const NRMSE_RANGE_Q_MOBILE_C: [f64; 2] = [4000.0, 7000.0];
pub const NRMSE_RANGE_R_O_OHM: [f64; 2] = [0.1, 0.2];

/// Accumulates squared normalised parameter errors over steps (Table 1's metric).
#[derive(Clone, Debug, Default)]
pub struct NrmseAccumulator {
    pub n: u64,
    pub sq_q_mobile: f64,
    pub sq_r_o: f64,
}

impl NrmseAccumulator {
    #[inline]
    pub fn add(&mut self, estimate: &Degradation, truth: &Degradation) {
        let eq = (estimate.q_mobile_c - truth.q_mobile_c) / (NRMSE_RANGE_Q_MOBILE_C[1] - NRMSE_RANGE_Q_MOBILE_C[0]);
        let er = (estimate.r_o_ohm - truth.r_o_ohm) / (NRMSE_RANGE_R_O_OHM[1] - NRMSE_RANGE_R_O_OHM[0]);
        self.n += 1;
        self.sq_q_mobile += eq * eq;
        self.sq_r_o += er * er;
    }

    /// (qMobile, Ro) normalised RMSE in %.
    pub fn pct(&self) -> (f64, f64) {
        let n = self.n.max(1) as f64;
        (100.0 * (self.sq_q_mobile / n).sqrt(), 100.0 * (self.sq_r_o / n).sqrt())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::dataset::{generate, ExperimentDef, Grid};

    #[test]
    fn apparent_resistance_reads_ro_off_the_measured_state_at_every_load() {
        // Vo relaxes to i Ro within a few of its 6 s time constants: past the first 40 s, Vo / i is Ro
        // whatever the load (the point of the feature: no division left for the policy to extrapolate).
        let (ds, spec, _) = tiny();
        for traj in ds.trajectories.iter().filter(|t| t.len() > 80) {
            let row = 40 + (traj.len() - 40) / 2;
            let x = state_at(traj, row);
            let r = apparent_resistance_ohm(x[idx::V_O], traj.voltage_v[row], traj.load_w);
            let ro = traj.degradation.r_o_ohm;
            assert!((r - ro).abs() < 0.01 * ro, "load {} W: Vo/i {r} vs Ro {ro}", traj.load_w);
        }
        // The feature is normalised with training statistics and lands in the last slot.
        let traj = &ds.trajectories[0];
        let mut obs = [0f32; crate::wire::MAX_OBS];
        let x_hat = electro(&model_state_at(&BatteryModel::default(), traj, 10));
        ObservationKind::FullStateOhmic.build(&spec.scales, &x_hat, traj, 11, &mut obs);
        let r = apparent_resistance_ohm(state_at(traj, 11)[idx::V_O], traj.voltage_v[11], traj.load_w);
        let want = (r - spec.scales.r_app_mean_ohm) / spec.scales.r_app_std_ohm;
        assert!((f64::from(obs[2 * N_STATE + 1]) - want).abs() < 1e-5);
        assert!(spec.scales.r_app_std_ohm > 1e-3 && spec.scales.r_app_mean_ohm > 0.05);
    }

    fn tiny() -> (Dataset, MdpSpec, BatteryModel) {
        let def = ExperimentDef {
            experiment: Experiment::Multi,
            q_mobile_c: Grid { start: 4000.0, end: 7000.0, n: 3 },
            r_o_ohm: Grid { start: 0.1, end: 0.2, n: 2 },
            loads_w: Grid { start: 8.0, end: 16.0, n: 9 },
            n_test_loads: 3,
            dt_s: 1.0,
            max_steps: 100_000,
        };
        let model = BatteryModel::default();
        let ds = generate(&def, &model).unwrap();
        let spec = MdpSpec::new(Experiment::Multi, &EnvConfig::default(), &ds);
        (ds, spec, model)
    }

    #[test]
    fn action_map_roundtrips_and_clamps() {
        let m = ActionMap::from_config(Experiment::Multi, &EnvConfig::default());
        let d = Degradation { q_mobile_c: 5234.0, r_o_ohm: 0.137 };
        let back = m.to_degradation(&m.to_action(&d));
        assert!((back.q_mobile_c - 5234.0).abs() < 1e-3 && (back.r_o_ohm - 0.137).abs() < 1e-7);
        let clamped = m.to_degradation(&[-5.0, 5.0]);
        assert!((clamped.q_mobile_c - 3500.0).abs() < 1e-9 && (clamped.r_o_ohm - 0.22).abs() < 1e-12);
        let q = ActionMap::from_config(Experiment::SingleQ, &EnvConfig::default());
        assert_eq!(q.dim(), 1);
        assert_eq!(q.to_degradation(&[0.0]).r_o_ohm, 0.117215);
        let r = ActionMap::from_config(Experiment::SingleR, &EnvConfig::default());
        assert_eq!(r.to_degradation(&[0.0]).q_mobile_c, 7600.0);
    }

    #[test]
    fn true_parameters_give_zero_cost_and_wrong_ones_do_not() {
        let (ds, spec, model) = tiny();
        let traj = ds.train().next().unwrap();
        let truth = spec.actions.to_action(&traj.degradation);
        let mut wrong = truth;
        wrong[1] += 0.3;
        let (mut c_true, mut c_wrong) = (0.0, 0.0);
        let mut x_true = model_state_at(&model, traj, 100);
        let mut x_wrong = x_true;
        for t in 100..116 {
            let x_next = state_at(traj, t + 1);
            let (n1, c1) = spec.transition(&model, &x_true, &truth, traj.load_w, &x_next);
            let (n2, c2) = spec.transition(&model, &x_wrong, &wrong, traj.load_w, &x_next);
            x_true = n1;
            x_wrong = n2;
            c_true += c1;
            c_wrong += c2;
        }
        // f32 storage of the trajectory is the only error under the true parameters.
        assert!(c_true < 1e-3, "true-parameter cost {c_true}");
        assert!(c_wrong > 100.0 * c_true.max(1e-6), "wrong {c_wrong} vs true {c_true}");
    }

    #[test]
    fn scales_normalise_training_states() {
        let (ds, spec, _) = tiny();
        let mut acc = [0f64; N_STATE];
        let mut n = 0.0;
        let mut buf = [0f32; N_STATE];
        for t in ds.train() {
            for row in 0..t.len() {
                spec.scales.normalise_state(&state_at(t, row), &mut buf);
                for k in 0..N_STATE {
                    acc[k] += f64::from(buf[k]).powi(2);
                }
                n += 1.0;
            }
        }
        for (k, a) in acc.iter().enumerate() {
            let var = a / n;
            assert!((var - 1.0).abs() < 1e-2, "state {k}: normalised variance {var}");
        }
    }

    #[test]
    fn env_windows_reset_and_never_index_past_the_trajectory() {
        let (ds, spec, model) = tiny();
        let train = ds.train_indices();
        let mut rng = SplitMix64(7);
        let mut env = CalibrationEnv::new(&spec, &model, &ds, &train, &mut rng);
        let mut obs = vec![0f32; spec.obs_dim()];
        let mut next = vec![0f32; spec.obs_dim()];
        let (mut dones, mut steps_in_window, mut max_window) = (0, 0, 0);
        for _ in 0..20_000 {
            env.observe(&spec, &ds, &mut obs);
            assert!(obs.iter().all(|v| v.is_finite()));
            let s = env.step(&spec, &model, &ds, &train, &[0.1, -0.2], &mut next, &mut rng);
            assert!(s.cost.is_finite() && s.cost >= 0.0);
            steps_in_window += 1;
            if s.window_done {
                dones += 1;
                max_window = max_window.max(steps_in_window);
                steps_in_window = 0;
            }
        }
        assert!(dones > 20_000 / spec.window_steps - 10, "{dones} windows");
        assert_eq!(max_window, spec.window_steps);
    }

    #[test]
    fn rollout_with_the_true_parameters_has_zero_error_and_near_zero_cost() {
        let (ds, spec, model) = tiny();
        let traj = ds.test().next().unwrap();
        let truth = spec.actions.to_action(&traj.degradation);
        let mut acc = NrmseAccumulator::default();
        let mut max_cost: f64 = 0.0;
        rollout_calibrator(
            &spec,
            &model,
            traj,
            |_, a| a.copy_from_slice(&truth[..a.len()]),
            |_, est, c| {
                acc.add(est, &traj.degradation);
                max_cost = max_cost.max(c);
            },
        );
        assert_eq!(acc.n as usize, traj.len() - 1);
        let (q, r) = acc.pct();
        assert!(q < 1e-3 && r < 1e-3, "{q} {r}");
        assert!(max_cost < 1e-3, "{max_cost}");
        // A constant wrong guess has the error the metric says: 300 C off is 10 % of the 3000 C range.
        let mut wrong = NrmseAccumulator::default();
        let guess = Degradation { q_mobile_c: traj.degradation.q_mobile_c + 300.0, ..traj.degradation };
        wrong.add(&guess, &traj.degradation);
        assert!((wrong.pct().0 - 10.0).abs() < 1e-9);
    }

    #[test]
    fn splitmix_normal_has_unit_variance() {
        let mut r = SplitMix64(3);
        let n = 200_000;
        let (mut s, mut q) = (0.0, 0.0);
        for _ in 0..n {
            let v = r.normal();
            s += v;
            q += v * v;
        }
        let mean = s / n as f64;
        assert!(mean.abs() < 0.01 && (q / n as f64 - 1.0).abs() < 0.02);
    }
}
