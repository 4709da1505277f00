//! The engine's hot loops a second time, compiled for AVX2 (x86-64-v3) and chosen at run time.
//!
//! The default build targets baseline x86-64 (SSE2), so the compiler vectorises the kernels
//! four floats wide; a CPU with AVX2 runs the same loops eight wide. The operations and their
//! order are the same (Rust never fuses `a * b + c` into an FMA on its own, and float sums are
//! not reordered), so both paths give bit-identical results: a test holds them equal.

use std::sync::atomic::{AtomicBool, Ordering};
#[cfg(target_arch = "x86_64")]
use std::sync::OnceLock;

/// Set by tests to run the baseline path on a CPU with AVX2.
static BASELINE_ONLY: AtomicBool = AtomicBool::new(false);

/// Whether the AVX2 path runs here.
pub fn avx2() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        static HAS: OnceLock<bool> = OnceLock::new();
        let has = *HAS.get_or_init(|| {
            std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma")
        });
        has && !BASELINE_ONLY.load(Ordering::Relaxed)
    }
    #[cfg(not(target_arch = "x86_64"))]
    false
}

/// Runs the baseline path even where AVX2 is there (`true`), or the best one (`false`): for
/// the tests and the `train_step` bench, which compare the two.
pub fn baseline_only(on: bool) {
    BASELINE_ONLY.store(on, Ordering::Relaxed);
}

/// Calls `f` from a function compiled for AVX2 where the CPU has it: `f` and everything it
/// inlines (the kernels are `#[inline(always)]` for this) use the wider vectors.
#[inline(always)]
pub(crate) fn dispatch<R>(f: impl FnOnce() -> R) -> R {
    #[cfg(target_arch = "x86_64")]
    if avx2() {
        #[target_feature(enable = "avx2,fma")]
        unsafe fn wide<R>(f: impl FnOnce() -> R) -> R {
            f()
        }
        // SAFETY: `avx2()` checked that this CPU has AVX2 and FMA.
        return unsafe { wide(f) };
    }
    f()
}
