//! AVX2 dispatch of the element-wise kernels (the token-column kernels of `cols` and the
//! group norm of `norm`): the same code compiled for AVX2 where the CPU has it, the same bits
//! either way. A leaf module: `cols` and `norm` share it without naming each other.

/// Defines `$name($args)` running `$body($args)` compiled for AVX2 where the CPU has it.
macro_rules! avx2_dispatch {
    ($(#[$doc:meta])* fn $name:ident($($a:ident: $t:ty),* $(,)?) => $body:ident) => {
        $(#[$doc])*
        pub(crate) fn $name($($a: $t),*) {
            #[cfg(target_arch = "x86_64")]
            {
                /// The body compiled for AVX2.
                ///
                /// # Safety
                /// The CPU must support AVX2.
                #[allow(clippy::too_many_arguments)]
                #[target_feature(enable = "avx2")]
                unsafe fn avx2($($a: $t),*) {
                    $body($($a),*)
                }
                if std::arch::is_x86_feature_detected!("avx2") {
                    // SAFETY: the CPU supports AVX2, checked just above.
                    unsafe { avx2($($a),*) };
                    return;
                }
            }
            $body($($a),*)
        }
    };
}

pub(crate) use avx2_dispatch;
