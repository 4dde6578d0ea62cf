//! A calibrator run along whole trajectories (the paper's Fig. 1, part 2) and the learner's periodic
//! validation of a policy on them. Evaluation only: these read the true parameters to score, never to act.

use super::spec::{model_state_at, state_at, MdpSpec};
use crate::battery::{BatteryModel, Degradation};
use crate::dataset::{Dataset, Trajectory};
use crate::math::electro;
use crate::nrmse::NrmseAccumulator;

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

/// How a policy did on a set of trajectories.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PolicyScore {
    /// Mean one-step tracking error (unshaped): label-free, what a calibrator can know about itself.
    pub tracking_error: f64,
    /// Table-1 NRMSE of qMobile and Ro, % (reads the true parameters).
    pub nrmse_q_pct: f64,
    pub nrmse_r_pct: f64,
}

impl PolicyScore {
    /// The score `select` ranks policies by (lower is better).
    pub fn by(&self, select: crate::config::SelectBy) -> f64 {
        match select {
            crate::config::SelectBy::TrackingError => self.tracking_error,
            crate::config::SelectBy::Nrmse => 0.5 * (self.nrmse_q_pct + self.nrmse_r_pct),
        }
    }
}

/// Scores a policy's deterministic action along `trajectories` (indices into `ds`).
pub fn validate_policy(
    spec: &MdpSpec,
    model: &BatteryModel,
    ds: &Dataset,
    trajectories: &[usize],
    net: &crate::policy::PolicyNet,
) -> PolicyScore {
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
    PolicyScore { tracking_error: error_sum / n.max(1) as f64, nrmse_q_pct: q, nrmse_r_pct: r }
}
