//! The calibration MDP of the paper's Section 3.2.
//!
//! Observation s_t = [x_hat_t, x_{t+1}, u_{t+1}] (normalised), action = the calibrated degradation
//! parameters squashed to [-1, 1], transition x_hat_{t+1} = f(x_hat_t, a_t, u_{t+1}), cost
//! c_t = || x_hat_{t+1} - x_{t+1} || on the normalised state. One file per job: [`spec`] defines the MDP
//! (action map, observation, scales, transition and cost), [`env`] is one training environment, and
//! [`rollout`] runs a calibrator along whole trajectories and scores a policy for validation.

pub mod env;
pub mod rollout;
pub mod spec;

pub use env::{CalibrationEnv, EnvStep};
pub use rollout::{rollout_calibrator, validate_policy, PolicyScore};
pub use spec::{
    apparent_resistance_ohm, model_state_at, state_at, ActionMap, Calibrated, MdpSpec, ObsScales, ObservationKind,
};

#[cfg(test)]
mod tests {
    use super::*;
    use crate::battery::{BatteryModel, Degradation};
    use crate::config::EnvConfig;
    use crate::dataset::{generate, Dataset, Experiment, ExperimentDef, Grid, Split, ValidationDef};
    use crate::math::{electro, idx, N_STATE};
    use crate::nrmse::NrmseAccumulator;
    use rand::rngs::SmallRng;
    use rand::SeedableRng;

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
        ObservationKind::FullStateRoLeak.build(&spec.scales, &x_hat, traj, 11, &mut obs);
        let r = apparent_resistance_ohm(state_at(traj, 11)[idx::V_O], traj.voltage_v[11], traj.load_w);
        let want = (r - spec.scales.r_app_mean_ohm) / spec.scales.r_app_std_ohm;
        assert!((f64::from(obs[2 * N_STATE + 1]) - want).abs() < 1e-5);
        assert!(spec.scales.r_app_std_ohm > 1e-3 && spec.scales.r_app_mean_ohm > 0.05);
    }

    /// A small multi-parameter set: its training split and the MDP derived from it.
    fn tiny() -> (Dataset, MdpSpec, BatteryModel) {
        let model = BatteryModel::default();
        let ds = generate(&tiny_def(), &model, Split::Train).unwrap();
        let spec = MdpSpec::new(Experiment::Multi, &EnvConfig::default(), &ds);
        (ds, spec, model)
    }

    fn tiny_def() -> ExperimentDef {
        ExperimentDef {
            experiment: Experiment::Multi,
            q_mobile_c: Grid { start: 4000.0, end: 7000.0, n: 3 },
            r_o_ohm: Grid { start: 0.1, end: 0.2, n: 2 },
            loads_w: Grid { start: 8.0, end: 16.0, n: 9 },
            n_test_loads: 3,
            validation: ValidationDef {
                loads_w: vec![13.5],
                q_mobile_c: Grid::single(5500.0),
                r_o_ohm: Grid::single(0.15),
            },
            dt_s: 1.0,
            max_steps: 100_000,
        }
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
        let traj = &ds.trajectories[0];
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
        for t in &ds.trajectories {
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
        let mut rng = SmallRng::seed_from_u64(7);
        let mut env = CalibrationEnv::new(&spec, &model, &ds, &mut rng);
        let mut obs = vec![0f32; spec.obs_dim()];
        let mut next = vec![0f32; spec.obs_dim()];
        let (mut dones, mut steps_in_window, mut max_window) = (0, 0, 0);
        for _ in 0..20_000 {
            env.observe(&spec, &ds, &mut obs);
            assert!(obs.iter().all(|v| v.is_finite()));
            let s = env.step(&spec, &model, &ds, &[0.1, -0.2], &mut next, &mut rng);
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
        let (_, spec, model) = tiny();
        let test = generate(&tiny_def(), &model, Split::Test).unwrap();
        let traj = &test.trajectories[0];
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
}
