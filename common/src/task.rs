//! What a run trains and a policy file carries: the calibration task. Either the paper's setting (the
//! simulated cell's full internal state, noise-free: [`crate::mdp`]) or the measured-only setting
//! (voltage, current and temperature through a sensor model: [`crate::measured`]). Processes read it from
//! the run folder's `mdp.json`; a policy trained on one task is refused for the other, naming both.

use crate::mdp::MdpSpec;
use crate::measured::env::MeasuredSpec;
use serde::{Deserialize, Serialize};

// One per run or policy file, never in a hot loop: the size difference of the variants does not matter.
#[allow(clippy::large_enum_variant)]
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum Task {
    /// The paper's MDP: observation [x_hat_t, x_t+1, u_t+1] (and variants) of the simulated state.
    Paper(MdpSpec),
    /// The measured-only MDP: readings and the calibrator's own model.
    Measured(MeasuredSpec),
}

impl Task {
    pub fn obs_dim(&self) -> usize {
        match self {
            Task::Paper(m) => m.obs_dim(),
            Task::Measured(m) => m.obs_dim(),
        }
    }

    pub fn act_dim(&self) -> usize {
        match self {
            Task::Paper(m) => m.act_dim(),
            Task::Measured(m) => m.act_dim(),
        }
    }

    /// The observation's name, as the config spells it ("FullState", "FullStateRoLeak", "Measured").
    pub fn observation_name(&self) -> String {
        match self {
            Task::Paper(m) => format!("{:?}", m.observation),
            Task::Measured(_) => "Measured".into(),
        }
    }

    /// The config's observation as this module names tasks.
    pub fn observation_label(o: crate::config::Observation) -> &'static str {
        match o {
            crate::config::Observation::FullState => "FullState",
            crate::config::Observation::FullStateRoLeak => "FullStateRoLeak",
            crate::config::Observation::Measured => "Measured",
        }
    }

    pub fn paper(&self) -> Option<&MdpSpec> {
        match self {
            Task::Paper(m) => Some(m),
            Task::Measured(_) => None,
        }
    }

    pub fn measured(&self) -> Option<&MeasuredSpec> {
        match self {
            Task::Measured(m) => Some(m),
            Task::Paper(_) => None,
        }
    }

    /// Reads a task from JSON; a bare paper MDP (run folders written before tasks existed) reads as
    /// [`Task::Paper`].
    pub fn from_json(text: &str) -> Result<Self, serde_json::Error> {
        serde_json::from_str::<Task>(text)
            .or_else(|e| serde_json::from_str::<MdpSpec>(text).map(Task::Paper).map_err(|_| e))
    }
}
