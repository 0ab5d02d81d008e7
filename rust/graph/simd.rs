//! The run-time AVX2 check and the trampoline every SIMD path of the search goes through:
//! the same arithmetic either way, only wider where the CPU allows.

pub(crate) fn has_avx2() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::arch::is_x86_feature_detected!("avx2")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// Runs `f` compiled for AVX2 when the CPU has it, so the loops inlined into it (distance
/// tests, the rank sort) vectorise 4 wide. Same arithmetic either way: no FMA contraction.
#[inline(always)]
pub(crate) fn with_simd<R>(avx2: bool, f: impl FnOnce() -> R) -> R {
    #[cfg(target_arch = "x86_64")]
    if avx2 {
        #[target_feature(enable = "avx2")]
        unsafe fn wide<R>(f: impl FnOnce() -> R) -> R {
            f()
        }
        // SAFETY: avx2 is only true when the CPU has AVX2.
        return unsafe { wide(f) };
    }
    let _ = avx2;
    f()
}
