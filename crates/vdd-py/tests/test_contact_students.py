"""Saved students of the contact tasks act on their raw observations from Python exactly as
they do in Rust: each committed trace (tests/fixtures/contact, written by the vdd-tasks
example `saved_trace`; crates/vdd-tasks/tests/saved_traces.rs checks it against the
environment) is replayed through vdd.Policy.load."""

import json
import pathlib

import numpy as np
import pytest

import vdd

FIXTURES = pathlib.Path(__file__).resolve().parents[3] / "tests" / "fixtures" / "contact"


@pytest.mark.parametrize("task", ["pushing", "aligning"])
def test_a_saved_contact_student_acts_as_in_rust(task):
    trace = json.loads((FIXTURES / f"{task}.json").read_text())
    policy = vdd.Policy.load(FIXTURES / f"{task}.safetensors")
    observations = np.array(trace["observations"], dtype=np.float32)
    actions = np.array(trace["actions"], dtype=np.float32)
    assert policy.obs_dim == observations.shape[1] and policy.action_dim == actions.shape[1]
    assert len(actions) >= 10
    policy.seed(trace["seed"])
    policy.reset()
    got = np.stack([policy.act(o) for o in observations])
    np.testing.assert_array_equal(got, actions)
