//! A user's `Policy` whose `act` fails with its own error type: the rollout error keeps that
//! error at the end of its source chain, whichever way the policy is driven.

use std::error::Error;

use vdd_core::{CoreError, Policy};
use vdd_tasks::{EvalConfig, Stepping, TaskError, evaluate, evaluate_cloned};

/// The user's own error, with a source of its own.
#[derive(Debug, thiserror::Error)]
#[error("the controller lost its connection after {steps} steps")]
struct ControllerDown {
    steps: usize,
    #[source]
    cause: std::io::Error,
}

/// A policy on the Avoiding task's dimensions that fails at its fourth action.
#[derive(Clone, Default)]
struct Remote {
    steps: usize,
}

impl Remote {
    fn fail_or_count(&mut self) -> Result<(), CoreError> {
        self.steps += 1;
        if self.steps > 3 {
            let cause = std::io::Error::new(std::io::ErrorKind::ConnectionReset, "reset by peer");
            return Err(CoreError::implementor(ControllerDown { steps: self.steps - 1, cause }));
        }
        Ok(())
    }
}

impl Policy for Remote {
    fn obs_dim(&self) -> usize {
        4
    }
    fn action_dim(&self) -> usize {
        2
    }
    fn reset(&mut self) {
        self.steps = 0;
    }
    fn act_into(&mut self, _obs: &[f32], action: &mut [f32]) -> Result<(), CoreError> {
        self.fail_or_count()?;
        action.fill(0.0);
        Ok(())
    }
    fn act_batch(
        &mut self,
        _obs: faer::MatRef<'_, f32>,
        mut actions: faer::MatMut<'_, f32>,
    ) -> Result<(), CoreError> {
        self.fail_or_count()?;
        actions.fill(0.0);
        Ok(())
    }
}

/// Walks the source chain of `e` to the user's error and checks it and its own source.
fn check_chain(e: &TaskError) {
    assert!(matches!(e, TaskError::Policy { episode: 0, step: 3, .. }), "{e:?}");
    let mut chain: Vec<&(dyn Error + 'static)> = Vec::new();
    let mut next = e.source();
    while let Some(s) = next {
        chain.push(s);
        next = s.source();
    }
    let user = chain
        .iter()
        .find_map(|s| s.downcast_ref::<ControllerDown>())
        .unwrap_or_else(|| panic!("the user's error is not in the chain of {e}"));
    assert_eq!(user.steps, 3);
    let last = chain.last().unwrap().downcast_ref::<std::io::Error>().unwrap();
    assert_eq!(last.kind(), std::io::ErrorKind::ConnectionReset);
    assert!(e.to_string().contains("lost its connection"), "{e}");
}

#[test]
fn a_policy_error_surfaces_through_rollouts_with_its_source() {
    for stepping in [Stepping::PerEpisode, Stepping::Lockstep { batch_size: 2 }] {
        let cfg = EvalConfig { n_rollouts: 2, seed: 0, stepping, record: false };
        check_chain(&evaluate(&mut Remote::default(), &cfg).unwrap_err());
        check_chain(&evaluate_cloned(&Remote::default(), 2, &cfg).unwrap_err());
    }
}
