"""The whole trip from Python: a LeRobot diffusion policy imported (the committed lerobot 0.6.1
fixture: U-Net 16/32/48, two observation steps of 7 features, chunks of 16 two-D actions, DDPM
100 steps), distilled in Rust on states built from a user's own episodes, and the student acting
on raw observations, saved and loaded."""

import importlib.util
from pathlib import Path

import numpy as np
import pytest

import vdd

ROOT = Path(__file__).resolve().parents[3]
FIXTURE = ROOT / "tests" / "fixtures" / "import" / "lerobot_unet_ddpm"


def episodes(n=3, steps=12, seed=0):
    """A user's episodes: raw observations (T, 7) and actions (T, 2), as from a LeRobotDataset
    (observation.state then observation.environment_state, concatenated per step)."""
    rng = np.random.default_rng(seed)
    obs = [rng.uniform(-1.0, 1.0, (steps, 7)).astype(np.float32) for _ in range(n)]
    act = [np.cumsum(rng.normal(0.0, 0.1, (steps, 2)), axis=0).astype(np.float32) for _ in range(n)]
    return obs, act


@pytest.fixture(scope="module")
def teacher():
    # DDIM with 4 steps for the plan's teacher samples: seconds, not minutes, on CI's 2 cores.
    return vdd.import_lerobot(str(FIXTURE), sampler="ddim:4")


@pytest.fixture(scope="module")
def student(teacher):
    obs, act = episodes()
    states, chunks = teacher.training_windows(obs, act)
    return vdd.distill(
        teacher,
        states,
        actions=chunks,
        experts=2,
        iterations=10,
        teacher_samples=128,
        seed=0,
    )


def test_the_imported_teacher_states_its_shapes(teacher):
    assert teacher.kind == "unet1d" and teacher.source == "lerobot"
    assert teacher.noise_convention == "time"
    assert teacher.noise_range == (1.0, 100.0)
    assert (teacher.obs_dim, teacher.obs_window) == (7, 2)
    assert (teacher.step_action_dim, teacher.action_chunk) == (2, 16)
    assert (teacher.execute_steps, teacher.chunk_start) == (8, 1)
    assert (teacher.state_dim, teacher.action_dim) == (14, 32)
    assert teacher.sampler == "ddim:4" and teacher.obs_map is None
    assert "unet1d" in repr(teacher)


def test_training_windows_follow_lerobots_delta_timestamps(teacher):
    obs, act = episodes(n=2, steps=5)
    states, chunks = teacher.training_windows(obs, act)
    assert states.shape == (10, 14) and chunks.shape == (10, 32)
    # Step 0 of episode 0: the window repeats the first observation; the chunk starts one step
    # back (clamped), so its first two actions are the first action.
    np.testing.assert_array_equal(states[0], np.concatenate([obs[0][0], obs[0][0]]))
    np.testing.assert_array_equal(chunks[0, :2], act[0][0])
    np.testing.assert_array_equal(chunks[0, 2:4], act[0][0])
    # Step 3 of episode 1: observations 2 and 3, actions 2, 3, 4, 4, ...
    np.testing.assert_array_equal(states[8], np.concatenate([obs[1][2], obs[1][3]]))
    np.testing.assert_array_equal(chunks[8, :6], np.concatenate([act[1][2], act[1][3], act[1][4]]))
    np.testing.assert_array_equal(chunks[8, -2:], act[1][4])


def test_the_teachers_score_takes_raw_windows_and_chunks(teacher):
    obs, act = episodes(n=1, steps=4)
    states, chunks = teacher.training_windows(obs, act)
    score = teacher(chunks, states, np.full(len(states), 10.0))
    assert score.shape == chunks.shape and score.dtype == np.float32
    assert np.all(np.isfinite(score))


def test_the_teacher_samples_raw_chunks_reproducibly(teacher):
    obs, act = episodes(n=1, steps=3)
    states, _ = teacher.training_windows(obs, act)
    a = teacher.sample(states, seed=3)
    assert a.shape == (3, 32) and np.all(np.isfinite(a))
    np.testing.assert_array_equal(a, teacher.sample(states, seed=3))
    assert not np.array_equal(a, teacher.sample(states, seed=4))


def test_the_distilled_student_acts_on_raw_observations(student):
    assert (student.obs_dim, student.action_dim) == (7, 2)
    assert (student.obs_window, student.action_chunk) == (2, 16)
    assert student.num_experts == 2
    obs, _ = episodes(n=1, steps=10, seed=1)
    student.reset()
    actions = np.stack([student.act(o) for o in obs[0]])
    assert actions.shape == (10, 2) and np.all(np.isfinite(actions))
    lg, mu, L = student.components(np.concatenate([obs[0][0], obs[0][1]])[None])
    assert (lg.shape, mu.shape, L.shape) == ((1, 2), (1, 2, 32), (1, 2, 32, 32))
    batch = student.act_batch(obs[0][:3])
    assert batch.shape == (3, 2)


def test_the_student_saves_and_loads(student, tmp_path):
    path = tmp_path / "student.safetensors"
    student.save(str(path))
    loaded = vdd.Policy.load(str(path))
    assert (loaded.obs_window, loaded.action_chunk) == (2, 16)
    window = np.random.default_rng(2).uniform(-1, 1, (4, 14)).astype(np.float32)
    for a, b in zip(student.components(window), loaded.components(window)):
        np.testing.assert_array_equal(a, b)


def test_a_teacher_file_round_trips_through_load_teacher(teacher, tmp_path):
    path = tmp_path / "teacher.safetensors"
    teacher.save(str(path))
    again = vdd.load_teacher(str(path), sampler="ddpm")
    assert again.kind == "unet1d" and again.sampler == "ddpm"
    again.set_sampler("ddim:10")
    assert again.sampler == "ddim:10"
    with pytest.raises(ValueError, match="sampler"):
        again.set_sampler("ddim:1000")  # more steps than the 100 trained
    obs, act = episodes(n=1, steps=3)
    states, chunks = teacher.training_windows(obs, act)
    levels = np.full(len(states), 5.0)
    np.testing.assert_array_equal(teacher(chunks, states, levels), again(chunks, states, levels))
    # And a LeRobot directory through load_teacher is the same import.
    assert vdd.load_teacher(str(FIXTURE)).action_dim == 32


def test_bad_inputs_are_refused_naming_the_problem(teacher, tmp_path):
    with pytest.raises(ValueError, match="is not a directory"):
        vdd.import_lerobot(str(tmp_path / "no_such_policy"))
    with pytest.raises(ValueError, match="does not exist"):
        vdd.load_teacher(str(tmp_path / "no_such_teacher.safetensors"))
    with pytest.raises(vdd.VddError, match="config.json"):
        vdd.import_lerobot(str(tmp_path))  # a directory without LeRobot's files
    with pytest.raises(ValueError, match="sampler"):
        vdd.import_lerobot(str(FIXTURE), sampler="ddim")
    with pytest.raises(ValueError, match="sampler"):
        vdd.import_lerobot(str(FIXTURE), sampler="ddim:1000")
    with pytest.raises(ValueError, match="obs_map"):
        vdd.import_lerobot(str(FIXTURE), obs_map="observation.state=0..3;observation.environment_state=4..7")
    with pytest.raises(ValueError, match=r"observation windows of 2 steps × 7 features = 14 wide"):
        vdd.distill(teacher, np.zeros((4, 7)), iterations=1)
    with pytest.raises(ValueError, match="action_dim=3 but the teacher's actions are 32 wide"):
        vdd.distill(teacher, np.zeros((4, 14)), action_dim=3, iterations=1)
    with pytest.raises(ValueError, match=r"observations\[0\]: expected shape \(n, 7\)"):
        teacher.training_windows([np.zeros((5, 6))], [np.zeros((5, 2))])
    with pytest.raises(ValueError, match="episode 0: 5 observations and 4 actions"):
        teacher.training_windows([np.zeros((5, 7))], [np.zeros((4, 2))])
    with pytest.raises(ValueError, match="clip_margin"):
        vdd.distill(lambda a, s, t: -a, np.zeros((4, 1)), action_dim=2, clip_margin=0.5)
    with pytest.raises(ValueError, match=r"pass them as actions= .* or clip_margin=None"):
        vdd.distill(teacher, np.zeros((4, 14)), iterations=1)


def test_a_teacher_with_an_observation_map_is_not_distilled_silently(tmp_path):
    mapped = vdd.import_lerobot(
        str(FIXTURE), obs_map="observation.state=3..7;observation.environment_state=0..3"
    )
    assert mapped.obs_map == "observation.state=3,4,5,6;observation.environment_state=0,1,2"
    by_dict = vdd.import_lerobot(
        str(FIXTURE),
        obs_map={"observation.state": range(3, 7), "observation.environment_state": [0, 1, 2]},
    )
    assert by_dict.obs_map == mapped.obs_map
    obs, act = episodes(n=1, steps=4)
    states, chunks = mapped.training_windows(obs, act)
    # The window is mapped: the policy's features in its order.
    np.testing.assert_array_equal(states[0, :7], np.concatenate([obs[0][0][3:], obs[0][0][:3]]))
    with pytest.raises(ValueError, match="observation map"):
        vdd.distill(mapped, states, actions=chunks, iterations=1)


@pytest.mark.skipif(
    importlib.util.find_spec("lerobot_policy_vdd") is not None,
    reason="the LeRobot plugin is installed (its own script checks the round trip)",
)
def test_save_pretrained_without_the_lerobot_plugin_says_what_to_install(student, tmp_path):
    with pytest.raises(ImportError, match="lerobot_policy_vdd"):
        student.save_pretrained(str(tmp_path / "out"), str(FIXTURE))
