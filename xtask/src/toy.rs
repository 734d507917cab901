//! `cargo xtask` command (not implemented yet).

/// Runs the command.
pub fn run(_args: &[String]) -> crate::XResult {
    Err("not implemented yet".into())
}
