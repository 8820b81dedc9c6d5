"""Environment families (mcrl.envs.FAMILIES) and every registered environment: trains or is refused in one line."""
import os
import warnings

import gymnasium as gym
import numpy as np
import pytest

from mcrl.analysis.divergence import reward_max
from mcrl.config import resolve_config
from mcrl.envs import FAMILIES, family_of, flatten_obs, inspect, make_env, register_envs, success_of, to_env_action
from mcrl.errors import MCRLError


def test_families_say_how_success_is_read_and_what_the_bound_needs():
    assert family_of("FetchPush-v4").name == "FetchPush" and family_of("FetchPush-v4").thesis_table == "FetchPush"
    assert family_of("FetchReach-v4").name == "Fetch" and family_of("FetchReach-v4").thesis_table is None
    assert (family_of("AntMaze_UMazeDense-v5").success_key, family_of("AntMaze_UMaze-v5").act_dim) == ("success", 8)
    assert family_of("Pendulum-v1") is None
    assert success_of({"is_success": np.array([1.0])}) == 1.0 and success_of({"success": True}) == 1.0
    assert success_of({"reward_ctrl": 0.1}) is None
    # the divergence bound reads the family: FetchPush's 0 before MC, AntMaze's 1; none for an unknown family
    assert reward_max({"env_id": "FetchPush-v4"}) == 0.0
    assert reward_max({"env_id": "AntMaze_UMazeDense-v5", "intrinsic_alpha": 0.2, "intrinsic_reward_high": 1.0}) == 1.0
    assert reward_max({"env_id": "Pendulum-v1"}) is None


@pytest.mark.parametrize("fam", FAMILIES, ids=lambda f: f.name)
def test_each_familys_facts_match_a_real_environment(fam):
    env_id = fam.example
    assert family_of(env_id) is fam
    env = make_env(resolve_config(None, {"env_id": env_id}))
    try:
        assert env.action_space.shape == (fam.act_dim,), env_id
        env.reset(seed=0)
        _, r, _, _, info = env.step(env.action_space.sample())
        assert fam.success_key in info and r <= fam.reward_max, env_id
    finally:
        env.close()


@pytest.mark.parametrize("env_id", ["AntMaze_UMazeDense-v5", "PointMaze_UMaze-v3"])
def test_a_maze_leaves_no_model_file_behind_and_still_runs(env_id):
    """gymnasium-robotics writes each maze's model to a new file in the temporary directory and keeps it; make_env
    and the video's make_render_env remove it once MuJoCo has read it, and the environment still steps."""
    from mcrl.video.gl import make_render_env

    for make in (lambda: make_env(resolve_config(None, {"env_id": env_id})), lambda: make_render_env(env_id)):
        env = make()  # one at a time, so a failing check still closes the env it made
        try:
            path = env.unwrapped.tmp_xml_file_path
            assert path.endswith(".xml") and not os.path.exists(path), path
            env.reset(seed=0)
            _, r, _, _, info = env.step(env.action_space.sample())
            assert "success" in info and np.isfinite(r)
        finally:
            env.close()
    # gymnasium-robotics itself still writes one: the test sees the file the fix removes
    raw = gym.make(env_id)
    try:
        assert os.path.exists(raw.unwrapped.tmp_xml_file_path)
    finally:
        os.unlink(raw.unwrapped.tmp_xml_file_path)
        raw.close()


def test_every_registered_environment_steps_or_is_refused_in_one_line():
    """Walk gymnasium's and gymnasium-robotics' registry as a new user would: make, inspect the spaces, one step of
    the loop's own conversions (no training). Anything else than success or a one-line MCRLError fails."""
    register_envs()
    ok, refused, broken = [], {}, {}
    for env_id in sorted(gym.registry):
        cfg = resolve_config(None, {"env_id": env_id})
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                env = make_env(cfg)
                try:
                    spec = inspect(env, cfg)
                    obs, _ = env.reset(seed=0)
                    assert flatten_obs(obs).shape == (spec.obs_dim,)
                    a = np.zeros(spec.act_dim, np.float32)
                    nxt, r, term, trunc, info = env.step(to_env_action(a, env, cfg.action_scale))
                    assert flatten_obs(nxt).shape == (spec.obs_dim,) and np.isfinite(float(r))
                    success_of(info)
                finally:
                    env.close()
            ok.append(env_id)
        except MCRLError as e:
            refused[env_id] = str(e)
        except Exception as e:  # noqa: BLE001 - the point: nothing else may escape
            broken[env_id] = f"{type(e).__name__}: {e}"
    assert not broken, broken
    assert all("\n" not in m and ":" in m for m in refused.values()), refused
    assert {"FetchPush-v4", "AntMaze_UMazeDense-v5", "Pendulum-v1", "HalfCheetah-v5"} <= set(ok)
    # the kinds of refusal a user meets, each naming why
    assert "Discrete action space" in refused["CartPole-v1"]
    assert "Dict spaces, not Boxes" in refused["FrankaKitchen-v1"]  # goals that are nested Dicts
    assert "cannot be made here" in refused["Hopper-v2"]  # needs mujoco_py


def test_a_nested_goal_environment_on_the_command_line_is_one_line_and_no_files(tmp_path, capsys):
    from mcrl.cli import main

    rc = main(["train", "--env", "FrankaKitchen-v1", "--steps", "10", "--out-dir", str(tmp_path / "runs")])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and len(err.splitlines()) == 1 and "FrankaKitchen-v1" in err and "Box" in err, err
    assert not (tmp_path / "runs").exists() or not any((tmp_path / "runs").iterdir())
