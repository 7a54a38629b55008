//! Embed libtorch's library directory as an rpath in every binary, test and bench of this
//! crate, so that they run without `LD_LIBRARY_PATH`. torch-sys reports the directory it linked
//! against (the PyTorch wheel in the project venv when built through `cargo xtask`).

fn main() {
    println!("cargo:rerun-if-env-changed=DEP_TCH_LIBTORCH_LIB");
    if let Ok(dir) = std::env::var("DEP_TCH_LIBTORCH_LIB") {
        println!("cargo:rustc-link-arg=-Wl,-rpath,{dir}");
    }
}
