//! Bakes an rpath to libtorch into this package's binaries, tests and benches (the one script all crates
//! that link tch share; see launch/libtorch_rpath.rs).
include!("../launch/libtorch_rpath.rs");
