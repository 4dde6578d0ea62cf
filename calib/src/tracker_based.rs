//! The calibrators built on a [`Tracker`] (the calibrator's own model, its fit window and observation): the
//! RL policy ([`RlCalibrator`], the pure-Rust forward pass), the fit without learning
//! ([`WindowFitCalibrator`], the ablation that shows what the policy adds to its features) and a model
//! whose parameters stay where they started ([`Uncalibrated`]: the prior, the previous cycle's fit, an
//! offline fit).

use crate::tracker::Tracker;
use crate::{Calibrator, Interval};
use bcal_common::battery::Degradation;
use bcal_common::math::ModelState;
use bcal_common::measured::scenario::Sample;
use bcal_common::measured::tracker::{ActionMode, TrackerSpec, OBS_DIM};
use bcal_common::policy::{PolicyNet, Scratch};

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
#[derive(Clone, Debug)]
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
#[derive(Clone, Debug)]
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
