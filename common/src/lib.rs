//! bcal-common: what every bcal process shares. The battery model ([`battery`]) and one discharge of it as
//! `bcal simulate` runs it ([`simulate`]), the paper's experiments and their train / validation / test splits
//! ([`dataset`]), the calibration MDP ([`mdp`]), the Table-1 metric ([`nrmse`]), the pure-Rust policy forward
//! pass ([`policy`]), the run configuration ([`config`]), the wire types ([`wire`]) and iceoryx2 services
//! ([`ipc`]), the math vocabulary ([`math`]), atomic file writes ([`fsutil`]), the stable hash ([`hash`]) and
//! file text as error messages show it ([`text`]). It never prints and never exits: errors are typed.

pub mod battery;
pub mod config;
pub mod dataset;
pub mod fsutil;
pub mod hash;
pub mod ipc;
pub mod lifetime;
pub mod math;
pub mod mdp;
pub mod measured;
pub mod nrmse;
pub mod policy;
pub mod simulate;
pub mod stats;
pub mod task;
pub mod text;
pub mod wire;
