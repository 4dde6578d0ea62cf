//! The direct mapping's inference as a calibrator: the same inputs the RL policy of the task's design sees
//! (the correction's filter statistics, or the window fit's features), and a network trained elsewhere on
//! true parameters (bcal-eval, in tch) that answers through the pure-Rust forward pass.

use crate::correction::Correction;
use crate::tracker_based::WindowFitCalibrator;
use crate::{Calibrator, Interval};
use bcal_common::battery::Degradation;
use bcal_common::math::ModelState;
use bcal_common::measured::env::{Design, MeasuredSpec};
use bcal_common::measured::scenario::Sample;
use bcal_common::measured::tracker::TrackerSpec;
use bcal_common::policy::{PolicyNet, Scratch};

/// What feeds the network: the RL policy's own observation, with no correction applied.
#[derive(Clone, Debug)]
#[allow(clippy::large_enum_variant)]
pub enum DirectInputs {
    Window(WindowFitCalibrator),
    Filter(Correction),
}

impl DirectInputs {
    /// The inputs of `task`'s design.
    pub fn of_task(task: &MeasuredSpec) -> Self {
        match task.design {
            Design::WindowFit => DirectInputs::Window(WindowFitCalibrator::new(&task.tracker)),
            Design::UkfCorrection => DirectInputs::Filter(Correction::of_task(task)),
        }
    }

    pub fn step(&mut self, s: &Sample) {
        match self {
            DirectInputs::Window(w) => w.step(s),
            DirectInputs::Filter(c) => c.ingest(s),
        }
    }

    /// The observation, written into `out` (the task's observation dimension).
    pub fn observe(&self, out: &mut [f32]) {
        match self {
            DirectInputs::Window(w) => w.tracker().observe(out),
            DirectInputs::Filter(c) => c.observe(out),
        }
    }

    /// The inputs' own spread of the two parameters, z units (the fit's or the filter's).
    fn sd_z(&self, spec: &TrackerSpec) -> Option<[f64; 2]> {
        match self {
            DirectInputs::Window(w) => w.tracker().stats().std_z(spec.noise_floor_v),
            DirectInputs::Filter(c) => {
                let v = c.ukf().param_cov_z();
                c.ukf().started().then(|| [v[0].sqrt(), v[2].sqrt()])
            }
        }
    }

    fn state_under(&self, d: &Degradation) -> Option<ModelState> {
        match self {
            DirectInputs::Window(w) => w.state_under(d),
            DirectInputs::Filter(c) => c.state_under(d),
        }
    }
}

/// The direct mapping as a calibrator: its inputs run, the network answers.
pub struct DirectCalibrator<'a> {
    inputs: DirectInputs,
    net: &'a PolicyNet,
    scratch: Scratch,
    obs: Vec<f32>,
    spec: TrackerSpec,
    interval_scale: [f64; 2],
    estimate: Degradation,
}

impl<'a> DirectCalibrator<'a> {
    /// The network `net` (outputs in action units, [-1, 1] over the ranges) on the inputs of `task`'s
    /// design; `interval_scale` multiplies the inputs' standard deviations around the network's answer.
    pub fn new(task: &MeasuredSpec, net: &'a PolicyNet, interval_scale: [f64; 2]) -> Self {
        Self {
            inputs: DirectInputs::of_task(task),
            scratch: Scratch::new(net.layout()),
            obs: vec![0.0; task.obs_dim()],
            net,
            spec: task.tracker.clone(),
            interval_scale,
            estimate: task.tracker.prior,
        }
    }
}

impl Calibrator for DirectCalibrator<'_> {
    fn step(&mut self, s: &Sample) {
        self.inputs.step(s);
        self.inputs.observe(&mut self.obs);
        let (mut mean, mut log_std) = ([0f32; 2], [0f32; 2]);
        self.net.forward(&self.obs, &mut self.scratch, &mut mean, &mut log_std);
        self.estimate = self.spec.from_z([f64::from(mean[0] + 1.0) * 0.5, f64::from(mean[1] + 1.0) * 0.5]);
    }
    fn estimate(&self) -> Degradation {
        self.estimate
    }
    fn interval(&self) -> Option<Interval> {
        // The inputs' spread around the network's answer, scaled on validation.
        let sd = self.inputs.sd_z(&self.spec)?;
        Some(interval_around(&self.spec, &self.estimate, sd, self.interval_scale))
    }
    fn state(&self) -> Option<ModelState> {
        self.inputs.state_under(&self.estimate)
    }
}

/// The interval `k` standard deviations (`sd_z`, z units) either side of `d`, inside the ranges.
pub fn interval_around(spec: &TrackerSpec, d: &Degradation, sd_z: [f64; 2], k: [f64; 2]) -> Interval {
    let z = spec.to_z(d);
    let lo = spec.from_z([z[0] - k[0] * sd_z[0], z[1] - k[1] * sd_z[1]]);
    let hi = spec.from_z([z[0] + k[0] * sd_z[0], z[1] + k[1] * sd_z[1]]);
    Interval { q_mobile_c: [lo.q_mobile_c, hi.q_mobile_c], r_o_ohm: [lo.r_o_ohm, hi.r_o_ohm] }
}
