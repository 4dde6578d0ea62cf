//! Writes the test policy of [`bcal_tests::write_test_policy`] to the path given: the Python package's
//! tests run `cargo run -p bcal-tests --example write_policy -- FILE` to get a policy file for
//! `bcal.Calibrator("rl", policy=FILE)` (Python cannot write one).

fn main() {
    let Some(path) = std::env::args_os().nth(1) else {
        eprintln!("usage: write_policy FILE.bcalpol");
        std::process::exit(2);
    };
    bcal_tests::write_test_policy(std::path::Path::new(&path));
}
