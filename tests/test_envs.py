"""The BioTac gymnasium environments: registration, gymnasium's checker, seeding, physics of the
observations and rewards, termination, the vector env against stand-alone environments, and the
offscreen rgb_array frames."""

from __future__ import annotations

from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from gymnasium.vector import VectorEnv
from gymnasium.wrappers import RenderCollection

import twin  # noqa: F401  (registers the environments)
from assets.indenters import get_indenter
from fe.electrodes import ElectrodeParameters
from fe.indentation import IndentationStepper
from twin.envs import ENV_IDS
from twin.envs.edge import EdgeFollowEnv
from twin.envs.fe_batch import IndentationBatch
from twin.envs.press import PressEnv
from twin.envs.render import open_gl_context
from twin.envs.vector import TactileVectorEnv
from twin.fe_models import shared_model

PRESS = np.array([0.0, 0.0, 1.0])


def test_importing_twin_registers_the_biotac_envs() -> None:
    ids = [env_id for env_id in gym.registry if "BioTac" in env_id]
    assert sorted(ids) == sorted(ENV_IDS) and len(ids) >= 2


@pytest.mark.parametrize("env_id", sorted(ENV_IDS))
def test_envs_pass_gymnasiums_checker(env_id: str, tmp_path: Path) -> None:
    # The checker re-makes the env in every render mode: "rerun" goes to a file, not a spawned viewer.
    env = gym.make(env_id, rerun_save=tmp_path / "check.rrd")
    check_env(env.unwrapped)
    assert (tmp_path / "check.rrd").stat().st_size > 0
    obs, _ = env.reset(seed=0)
    assert "force" not in obs and obs["electrodes"].shape == (19,) and obs["pdc"].shape == (1,)


def test_seeding_repeats_episodes_and_different_seeds_differ() -> None:
    env = PressEnv(max_steps=4)
    first = [env.reset(seed=7)[0]] + [env.step(PRESS)[0] for _ in range(3)]
    target = env.target_point.copy()
    again = [env.reset(seed=7)[0]] + [env.step(PRESS)[0] for _ in range(3)]
    assert np.array_equal(env.target_point, target)
    for a, b in zip(first, again, strict=True):
        for key in a:
            assert np.array_equal(a[key], b[key]), key
    env.reset(seed=8)
    assert not np.array_equal(env.target_point, target)


def test_pressing_raises_pressure_lowers_electrodes_and_the_reward_tracks_the_force() -> None:
    env = PressEnv(max_steps=30, standoff_mm=(0.3, 0.3), start_offset_mm=0.0, ft=True)
    obs, _ = env.reset(seed=3)
    assert np.all(obs["electrodes"] == 0.0) and obs["pdc"][0] == 0.0  # tared at the start
    forces, pdcs, rewards = [], [], []
    terminated = False
    while not terminated:
        obs, reward, terminated, truncated, info = env.step(PRESS)
        assert not truncated and not info.get("fe_failed")
        forces.append(np.linalg.norm(info["force_n"]))
        pdcs.append(obs["pdc"][0])
        rewards.append(reward)
        if not terminated:
            assert obs["force"] == pytest.approx(info["force_n"], abs=0.06)  # F/T: FE force + 0.01 N noise
            expected = -abs(forces[-1] - env.target_force) - env.lateral_weight * info["lateral_mm"]
            assert reward == pytest.approx(expected)
    assert forces[-1] > env.force_limit_n and rewards[-1] < -env.limit_penalty + 1e-9  # force limit ends it
    loaded = [f for f in forces if f > 0.0]
    assert len(loaded) >= 3 and np.all(np.diff(loaded) > 0.0)  # the force grows with depth
    assert pdcs[-2] > pdcs[0] + 50  # and so does the fluid pressure
    assert obs["electrodes"].min() < -100  # the skin approaches the electrodes: counts go down
    assert obs["tip"][2] == pytest.approx(-0.3 + len(forces) * env.max_step_mm, abs=1e-4)


def test_sensor_parameters_set_the_electrode_read_out() -> None:
    quiet = {"noise_std": 0.0, "pdc_noise_std": 0.0}
    tared = []
    for gain in (1.0, 2.0):
        env = PressEnv(sensor_params=ElectrodeParameters(gain=np.full(19, gain), **quiet), start_offset_mm=0.0)
        env.reset(seed=4)
        for _ in range(5):
            obs = env.step(PRESS)[0]
        tared.append(obs["electrodes"])
    assert tared[0].min() < -30
    assert np.allclose(tared[1], 2.0 * tared[0], atol=1.0)  # tared counts scale with the gain (ADC rounding)


def test_episodes_truncate_at_max_steps_and_bad_input_is_refused() -> None:
    env = PressEnv(max_steps=2)
    with pytest.raises(RuntimeError, match="reset"):
        env.step(PRESS)
    env.reset(seed=1)
    assert not env.step(-PRESS)[3]
    assert env.step(-PRESS)[3]
    with pytest.raises(ValueError, match="3 finite"):
        env.step(np.array([0.0, np.nan, 1.0]))
    with pytest.raises(ValueError, match="target_force_n"):
        PressEnv(target_force_n=(2.0, 1.0))
    with pytest.raises(ValueError, match="render_mode"):
        PressEnv(render_mode="human")


def test_edge_env_hides_the_edge_direction_and_rewards_progress_along_it() -> None:
    env = EdgeFollowEnv(max_steps=12, standoff_mm=(0.2, 0.2))
    obs, _ = env.reset(seed=5)
    assert set(obs) == {"electrodes", "pdc", "tip"}  # nothing reveals the yaw
    axis = env._rotation[:, 0]
    for _ in range(3):  # press up into light contact
        obs, reward, terminated, _, info = env.step(np.array([0.0, 0.0, 0.5]))
    assert not terminated and info["in_window"] and obs["electrodes"].min() < -20
    along = np.array([axis[0], axis[1], 0.0]) / np.abs(axis[:2]).max()
    obs, reward, terminated, _, info = env.step(along)
    assert info["in_window"] and reward == pytest.approx(env.max_step_mm * np.linalg.norm(along), rel=1e-6)


def test_vector_env_matches_stand_alone_envs_and_autoresets_next_step() -> None:
    """The vector env on warp's CPU device gives each sub-environment what it gets alone."""
    n, seed = 3, 11
    actions = np.array([[0.0, 0.0, 1.0], [0.5, -0.5, 1.0], [0.0, 0.0, -1.0]])
    # All n sub-environments are the systems of one batched FE engine on warp's CPU device; each
    # stand-alone env below is a one-system engine: the batch must not couple them.
    vec = gym.make_vec("BioTacPress-v0", num_envs=n, vectorization_mode="vector_entry_point", max_steps=3, device="cpu")
    assert isinstance(vec, TactileVectorEnv) and isinstance(vec, VectorEnv) and vec.fe.device == "cpu"
    vec_obs, _ = vec.reset(seed=seed)
    vec_rewards, vec_done = [], []
    for _ in range(3):
        vec_obs, reward, terminated, truncated, _ = vec.step(actions)
        vec_rewards.append(reward)
        vec_done.append(terminated | truncated)
    assert np.all(vec_done[-1]) and not np.any(vec_done[0])
    for k in range(n):  # each sub-env alone, on its own FE slot: the same numbers
        env = PressEnv(max_steps=3)
        env.reset(seed=seed + k)
        for step in range(3):
            obs, reward, *_ = env.step(actions[k])
            assert reward == pytest.approx(vec_rewards[step][k], rel=1e-6, abs=1e-9)
        assert np.allclose(obs["electrodes"], vec_obs["electrodes"][k], atol=1e-3)
    # NEXT_STEP autoreset: the step after the end starts new episodes, reward 0, tip back off the skin.
    obs, reward, terminated, truncated, _ = vec.step(actions)
    assert np.all(reward == 0.0) and not np.any(terminated | truncated)
    assert np.all(obs["tip"][:, 2] < 0.0) and np.all(obs["pdc"] == 0.0)
    with pytest.raises(ValueError, match="actions must be"):
        vec.step(actions[:2])


def test_a_failed_slot_is_cut_back_like_the_one_system_stepper_while_the_others_go_on() -> None:
    model = shared_model(2.0)
    point = model.reference[np.argmin(model.reference[:, 2])]  # the pad's lowest vertex
    press = model.plan_trajectory(get_indenter("sphere_medium"), point, 0.0, 0.0, 0.0, 1.0)
    start = press.touch_point - 0.3e-3 * press.direction
    deep = press.touch_point + 4.0e-3 * press.direction  # one 4.3 mm jump: fails unless halved
    shallow = press.touch_point + 0.3e-3 * press.direction  # one increment that converges as it is
    uncut = IndentationStepper(model.inflated_skin(), "sphere_medium", None, "cpu", max_cuts=0)
    uncut.step(press.rotation, start)
    assert not uncut.step(press.rotation, deep).converged
    alone = model.stepper("sphere_medium")
    alone.step(press.rotation, start)
    evaluations = alone.engine.shell.counters["evaluations"]
    reference = alone.step(press.rotation, deep)
    assert reference.converged and np.linalg.norm(reference.force) > 4.0
    rounds_alone = [alone.engine.shell.counters["evaluations"] - evaluations]  # one evaluation per Newton round
    one = IndentationBatch(model, ["sphere_medium"])
    one.step_batch(press.rotation[None], start[None])
    one.step_batch(press.rotation[None], shallow[None])
    rounds_alone.append(one.rounds)
    batch = IndentationBatch(model, ["sphere_medium"] * 2)
    rotations = np.stack([press.rotation] * 2)
    batch.step_batch(rotations, np.stack([start, start]))
    out = batch.step_batch(rotations, np.stack([deep, shallow]))
    assert np.all(out.converged)
    assert out.force[0] == pytest.approx(reference.force, rel=1e-6, abs=1e-9)
    assert np.allclose(out.displacement[0], reference.displacement, atol=1e-12)
    assert 0.0 < np.linalg.norm(out.force[1]) < 0.5 * np.linalg.norm(reference.force)
    # Continuously batched: slot 0 takes its halved steps while slot 1 iterates, so the call costs the
    # rounds of the slower slot alone (a lock-step schedule would add slot 1's rounds to slot 0's detours).
    assert min(rounds_alone) > 0 and batch.rounds == max(rounds_alone)


def test_a_device_warp_does_not_have_is_one_line() -> None:
    with pytest.raises(ValueError, match="warp has no device 'tpu:3'") as error:
        gym.make("BioTacPress-v0", device="tpu:3")
    assert "\n" not in str(error.value)


@pytest.fixture(scope="module")
def offscreen_gl() -> None:
    """Skip (saying why) where no offscreen OpenGL backend opens; the error names MUJOCO_GL."""
    try:
        open_gl_context(8, 8).free()
    except RuntimeError as error:
        pytest.skip(str(error))


def _changed(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(H, W) mask of pixels whose colour differs by more than 30 (sum of |RGB| differences)."""
    return np.abs(a.astype(int) - b.astype(int)).sum(axis=-1) > 30


def _red_mask(frame: np.ndarray) -> np.ndarray:
    """(H, W) bool: the strongly red pixels (the force arrow's colour; nothing else in the scene is red)."""
    return (frame[..., 0] > 120) & (frame[..., 1] < 90) & (frame[..., 2] < 90)


def _red_pixels(frame: np.ndarray) -> int:
    """Number of strongly red pixels."""
    return int(_red_mask(frame).sum())


def test_rgb_array_frames_show_the_skin_deformation_and_the_force(offscreen_gl: None) -> None:
    env = RenderCollection(
        gym.make("BioTacPress-v0", render_mode="rgb_array", standoff_mm=(0.3, 0.3), start_offset_mm=0.0)
    )
    assert "rgb_array" in env.metadata["render_modes"]
    env.reset(seed=3)
    terminated, steps = False, 0
    while not terminated and steps < 9:
        _, _, terminated, _, info = env.step(PRESS)
        steps += 1
    frames = env.render()  # RenderCollection: one frame per reset and step
    assert len(frames) == steps + 1
    assert all(f.shape == (240, 320, 3) and f.dtype == np.uint8 for f in frames)
    free, pressed = frames[0], frames[-1]
    assert np.linalg.norm(info["force_n"]) > 1.0 and _changed(free, pressed).mean() > 0.02
    # The same state drawn twice is the same picture; the force arrow (red) appears only under load.
    painter, base = env.unwrapped._painter, env.unwrapped
    rotation, tip = base._pose()
    increment = base._last_increment
    assert np.array_equal(painter.render(increment.displacement, rotation, tip, increment.force), pressed)
    assert _red_pixels(pressed) > 20 and _red_pixels(free) == 0
    # The arrow ends at the tip, which the camera looks at (the frame's centre); the indenter and the
    # skin around it do not hide it.
    centre = np.array(pressed.shape[:2]) / 2
    assert np.linalg.norm(np.argwhere(_red_mask(pressed)) - centre, axis=1).min() < 0.03 * pressed.shape[1]
    # The skin's deformation is drawn: the undeformed skin with the indenter where it is now differs,
    # and around the tip, which the camera centres.
    undeformed = painter.render(np.zeros_like(increment.displacement), rotation, tip, increment.force)
    dent = np.argwhere(_changed(undeformed, pressed))
    assert len(dent) > 50
    assert np.linalg.norm(dent.mean(axis=0) - centre) < 0.15 * pressed.shape[1]
    env.close()


def test_record_video_writes_an_episode(offscreen_gl: None, tmp_path: Path) -> None:
    pytest.importorskip("moviepy", reason="gymnasium's RecordVideo encodes with moviepy, not installed here")
    from gymnasium.wrappers import RecordVideo

    folder = tmp_path / "videos"
    env = RecordVideo(gym.make("BioTacPress-v0", render_mode="rgb_array", max_steps=3), str(folder))
    env.reset(seed=0)
    for _ in range(3):
        env.step(PRESS)
    env.close()
    videos = list(folder.glob("*.mp4"))
    assert len(videos) == 1 and videos[0].stat().st_size > 0


def test_rgb_array_without_an_opengl_backend_is_one_line_naming_mujoco_gl(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("MUJOCO_GL", "no_such_backend")
    with pytest.raises(RuntimeError, match="MUJOCO_GL") as error:
        PressEnv(render_mode="rgb_array")
    assert "\n" not in str(error.value)
    with pytest.raises(ValueError, match="render_mode"):
        TactileVectorEnv(PressEnv, 2, render_mode="rgb_array")
