//! The benchmarks of the experiment layer: what `cargo xtask bench robustness` measures
//! ([`robustness`]).

pub mod robustness;
