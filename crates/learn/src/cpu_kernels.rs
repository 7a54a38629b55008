//! Which of libtorch's vectorized CPU kernel sets runs: AVX2 unless the user chose.
//!
//! libtorch picks its kernels once per process, at the first operator call, from the CPU's
//! features or from `ATEN_CPU_CAPABILITY` (`default`, `avx2`, `avx512`). On the 2-core AMD EPYC
//! machines this project trains on, its AVX-512 ELU is the slow one: `Sleef_expm1f16_u10avx512f`
//! made `F.elu` on a `[24576, 256]` float tensor take 41 ms against 6.4 ms with the AVX2 kernel
//! (PyTorch 2.13, 2 threads; `exp` alone is as fast in both), and ELU follows every hidden layer
//! of both networks. With AVX2 a lift iteration's PPO update took 1.4 s instead of 2.6 s and its
//! act 0.15 s instead of 0.39 s (1024 worlds, see the README). Matrix products go through MKL,
//! which this choice does not touch.
//!
//! The choice is an environment variable because that is the only switch libtorch has, and it is
//! read once: [`prefer_avx2`] must run first thing in `main`, before any thread is started and
//! before any `tch` call. A user who sets `ATEN_CPU_CAPABILITY` keeps their choice.

/// libtorch's switch.
pub const CAPABILITY_VAR: &str = "ATEN_CPU_CAPABILITY";

/// Selects libtorch's AVX2 kernels on an x86-64 CPU that has AVX2, unless `ATEN_CPU_CAPABILITY`
/// is already set; returns the kernel set asked for, if any (for the run's log).
///
/// Call it at the start of `main`, while the process has one thread (it sets an environment
/// variable) and before libtorch has run an operator (it reads the variable once).
pub fn prefer_avx2() -> Option<String> {
    if let Some(chosen) = std::env::var_os(CAPABILITY_VAR) {
        return Some(chosen.to_string_lossy().into_owned());
    }
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        std::env::set_var(CAPABILITY_VAR, "avx2");
        return Some("avx2".into());
    }
    None
}
