//! Tests of the Block-Push environment, oracle and rollouts.
