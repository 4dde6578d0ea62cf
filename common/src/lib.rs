//! bcal-common: what every bcal process shares. The battery model ([`battery`]), the paper's experiments
//! ([`dataset`]) and the math vocabulary ([`math`]). It never prints and never exits: errors are typed.

pub mod battery;
pub mod dataset;
pub mod math;
