//! Bake an rpath to libtorch into this package's binaries, tests and benches, so
//! they run without LD_LIBRARY_PATH. LIBTORCH comes from .cargo/config.toml
//! (<repo>/.libtorch, made by launch/setup-libtorch.sh) or the environment.
//! `rustc-link-arg` only reaches this package's own targets: every crate that
//! links tch carries its own copy of this file, verbatim.
fn main() {
    println!("cargo:rerun-if-env-changed=LIBTORCH");
    let Some(libtorch) = std::env::var_os("LIBTORCH") else {
        println!("cargo:warning=LIBTORCH is not set: run launch/setup-libtorch.sh");
        return;
    };
    // The canonical path, so the rpath does not depend on the .libtorch symlink.
    let lib = match std::fs::canonicalize(&libtorch) {
        Ok(dir) => dir.join("lib"),
        Err(e) => {
            let shown = std::path::Path::new(&libtorch).display();
            println!("cargo:warning=LIBTORCH={shown}: {e}; run launch/setup-libtorch.sh");
            return;
        }
    };
    println!("cargo:rerun-if-changed={}", lib.display());
    let os = std::env::var("CARGO_CFG_TARGET_OS").unwrap_or_default();
    if os == "linux" || os == "macos" {
        println!("cargo:rustc-link-arg=-Wl,-rpath,{}", lib.display());
    }
}
