"""Policy.export_onnx: ONNX Runtime's outputs equal Policy.components."""

import numpy as np
import onnxruntime as ort
import pytest

import vdd
from conftest import four_modes_score


def run(path, obs):
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    assert [i.name for i in sess.get_inputs()] == ["obs"]
    assert [o.name for o in sess.get_outputs()] == ["log_gating", "means", "scale_tril"]
    return sess.run(None, {"obs": obs})


def test_onnx_runtime_matches_components(saved_policy, tmp_path):
    p = vdd.Policy.load(saved_policy)
    path = tmp_path / "policy.onnx"
    p.export_onnx(path)
    rng = np.random.default_rng(0)
    for n in (1, 7):  # the batch dimension is dynamic
        obs = rng.normal(size=(n, 1)).astype(np.float32)
        for got, want in zip(run(path, obs), p.components(obs)):
            assert got.shape == want.shape
            np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("kind", ["diagonal", "full"])
def test_learned_gating_and_normalised_states_export_too(kind, tmp_path):
    states = np.random.default_rng(1).normal(3.0, 2.0, size=(32, 3)).astype(np.float32)
    actions = np.random.default_rng(2).normal(size=(32, 2)).astype(np.float32)
    p = vdd.distill(four_modes_score, states, action_dim=2, experts=3, iterations=5,
                    actions=actions, gating="learned", expert_kind=kind)
    path = tmp_path / "policy.onnx"
    p.export_onnx(path)
    for got, want in zip(run(path, states), p.components(states)):
        np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-5)
