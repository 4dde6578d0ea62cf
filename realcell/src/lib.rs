//! bcal-realcell: real cells in real time. A measured discharge ([`record`]) is fed to a calibrator one
//! reading at a time, with no look-ahead, exactly as a battery management system would; at every reading
//! the calibrated model predicts when the voltage will reach the cut-off and how much charge the cell holds
//! ([`predict`], [`run`]); the predictions are scored against what the cycler measured on held-out cycles
//! ([`score`]) and reported ([`report`]). The same calibrators serve the simulator (bcal-eval) and real
//! data: the RL policy and the joint UKF behind one step interface, beside the doctor's offline fit and
//! the references a prognostics engineer would compare with. The library never prints.

pub mod calibrate;
pub mod carry;
pub mod cellspec;
pub mod interval;
pub mod predict;
pub mod prior;
pub mod recentre;
pub mod record;
pub mod recorded;
pub mod report;
pub mod run;
pub mod score;
#[cfg(test)]
mod testing;
pub mod tune;
