// Bake an rpath to libtorch into this package's binaries, tests and benches, so
// they run without LD_LIBRARY_PATH. LIBTORCH comes from .cargo/config.toml
// (<repo>/.libtorch, made by launch/setup-libtorch.sh) or the environment.
// `rustc-link-arg` only reaches the targets of the package whose build script
// prints it, so every crate that links tch has a build.rs that includes this file.
use std::path::Path;

fn main() {
    println!("cargo:rerun-if-env-changed=LIBTORCH");
    let Some(libtorch) = std::env::var_os("LIBTORCH") else {
        println!("cargo:warning=LIBTORCH is not set: run launch/setup-libtorch.sh");
        return;
    };
    // Watched through the symlink, so re-pointing .libtorch reruns this script;
    // while the path is missing, cargo reruns it on every build.
    let lib = Path::new(&libtorch).join("lib");
    println!("cargo:rerun-if-changed={}", lib.display());
    // The rpath holds the canonical path: it must not depend on the symlink.
    match lib.canonicalize() {
        Ok(lib) if matches!(std::env::var("CARGO_CFG_TARGET_OS").as_deref(), Ok("linux" | "macos")) => {
            println!("cargo:rustc-link-arg=-Wl,-rpath,{}", lib.display());
        }
        Ok(_) => {}
        Err(e) => println!("cargo:warning={}: {e}; run launch/setup-libtorch.sh", lib.display()),
    }
}
