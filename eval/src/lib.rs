//! bcal-eval: the evaluator. It runs the trained RL-LAC policy, a tuned unscented Kalman filter ([`ukf`])
//! and a supervised direct mapping ([`direct`]) along the same held-out (high-load) test trajectories,
//! scores them ([`metrics`]: the paper's Table-1 normalised RMSE, per-cycle error, convergence time, EOD
//! prediction error), times one step of each beside one battery-model step, and writes report.json,
//! report.md ([`report`]) and figures ([`plots`]) into the run folder ([`evaluate`]).
//!
//! [`summary`] puts several runs (seeds) side by side as mean and spread.
//!
//! It never prints and never exits: progress goes to a callback and errors are typed.

pub mod direct;
pub mod evaluate;
pub mod measured_eval;
pub mod measured_report;
pub mod metrics;
pub mod plots;
pub mod report;
pub mod summary;
pub mod ukf;

pub use evaluate::{evaluate, write_outputs, EvalError, EvalInput, EvalOptions, Evaluation, PolicyInput};
pub use report::Report;
