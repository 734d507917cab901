//! `exact`: the task's exact mixture (the toys), the teacher `vdd-exact` distils. Nothing is
//! trained; the task hands the mixture to the method with the data.

use vdd_diffusion::TeacherKind;

use super::TeacherSource;
use crate::capability::Capability;

/// The exact-mixture source.
pub struct Exact;

/// `exact`.
pub const EXACT: Exact = Exact;

impl TeacherSource for Exact {
    fn name(&self) -> &'static str {
        "exact"
    }
    fn kind(&self) -> Option<TeacherKind> {
        None
    }
    fn needs(&self) -> &'static [Capability] {
        &[Capability::ExactMixture]
    }
}
