//! The benchmarks of the experiment layer, what `cargo xtask bench robustness|teachers`
//! measures: the robustness benchmark of VDD's defaults ([`robustness`]) and the acceptance
//! checks and sampling latency of the learned toy teachers ([`teachers`]).

pub mod robustness;
pub mod teachers;
