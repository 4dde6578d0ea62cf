//! bcal-common: what every bcal process shares. The battery model ([`battery`]), the paper's experiments
//! ([`dataset`]), the calibration MDP ([`mdp`]), the pure-Rust policy forward pass ([`policy`]), the run
//! configuration ([`config`]), the wire types ([`wire`]), the math vocabulary ([`math`]) and file text as
//! error messages show it ([`text`]). It never prints and never exits: errors are typed.

pub mod battery;
pub mod config;
pub mod dataset;
pub mod ipc;
pub mod math;
pub mod mdp;
pub mod policy;
pub mod text;
pub mod wire;
