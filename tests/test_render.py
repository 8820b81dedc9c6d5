"""`mcrl render` on a trained FetchReach policy: frame counts, non-blank frames, and timeline values that
equal the KL the MC module computes for the rendered trajectory."""
import imageio.v3 as iio
import jax.numpy as jnp
import numpy as np
import pytest

from mcrl.algo import normaliser
from mcrl.algo.mc import gaussian_kl
from mcrl.cli import main
from mcrl.config import resolve_config
from mcrl.run.policy import load_policy
from mcrl.run.trainer import train
from mcrl.video import Timeline, make_render_env
from mcrl.video.render import record_episode


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    from tests.conftest import SMALL

    cfg = resolve_config("fetchreach-sacmc", {**SMALL, "total_steps": 250, "eval_every": 0})
    return train(cfg, tmp_path_factory.mktemp("r") / "run", progress=False)


def test_render_cli_writes_one_nonblank_frame_per_step(run_dir, tmp_path, capsys):
    out = tmp_path / "v.gif"
    assert main(["render", str(run_dir), "--episodes", "2", "--format", "gif", "--out", str(out)]) == 0
    frames = iio.imread(out)
    assert frames.shape[0] == 2 * 50  # two FetchReach episodes
    scene = frames[:, : frames.shape[1] // 2]
    assert all(f.std() > 10 for f in scene[::10])  # a real scene, not a blank or uniform image


def test_timeline_values_equal_the_mc_modules_kl(run_dir):
    cfg, agent, state = load_policy(run_dir)
    env = make_render_env(cfg.env_id)
    try:
        ep = record_episode(cfg, agent, state, env, seed=123)
    finally:
        env.close()
    # recompute independently from the recorded trajectory with the MC models' raw outputs
    s = jnp.asarray(ep["flat_obs"][:-1, : agent.intrinsic_dim])
    out = agent.intrinsic_net.models.forward(state.intrinsic.params, s, jnp.asarray(ep["policy_actions"]))
    kl = np.asarray(gaussian_kl(out.mu_t, out.log_std_t, out.mu_a, out.log_std_a).sum(-1))
    lo, hi = normaliser.bounds(state.norm, cfg.min_percentile, cfg.max_percentile)
    r_mc = np.asarray(normaliser.scale(jnp.asarray(kl), lo, hi, cfg.intrinsic_reward_low, cfg.intrinsic_reward_high))
    tl = Timeline(ep["series"], ep["success"], width=480)
    assert tl.T == ep["length"] == 50
    for t in (0, 17, 49):
        drawn = {name: value for name, value, _ in tl.annotations(t)}
        assert drawn["raw KL (nats)"] == pytest.approx(float(kl[t]), rel=1e-5)
        assert drawn["MC reward (normalised)"] == pytest.approx(float(r_mc[t]), rel=1e-5, abs=1e-6)
        assert drawn["extrinsic reward"] == ep["rewards"][t]


def test_timeline_mixes_the_rewards_at_the_weight_in_force(run_dir):
    """The last row is the reward the agent learns from, (1 - alpha) r_ext + alpha r_int, at the weight its schedule
    gives (the training loop passes it), named with that weight; without one given, the config's."""
    cfg, agent, state = load_policy(run_dir)
    env = make_render_env(cfg.env_id)
    try:
        ep = record_episode(cfg, agent, state, env, seed=123, alpha=0.13)
        plain = record_episode(cfg, agent, state, env, seed=123)
    finally:
        env.close()
    rows = ep["series"]
    assert list(rows)[-1] == "mixed reward, alpha 0.13" and list(plain["series"])[-1] == "mixed reward, alpha 0.2"
    np.testing.assert_allclose(rows["mixed reward, alpha 0.13"],
                               0.87 * ep["rewards"] + 0.13 * rows["MC reward (normalised)"], rtol=1e-12)


def test_render_errors(run_dir, tmp_path, capsys):
    assert main(["render", str(tmp_path)]) == 2
    assert "not a run directory" in capsys.readouterr().err
    assert main(["render", str(run_dir), "--checkpoint", "7"]) == 2
    assert "no checkpoint at step 7" in capsys.readouterr().err


def test_training_records_evaluation_videos_into_the_run_and_tensorboard(tmp_path):
    from tests.conftest import SMALL
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    from mcrl.video.render import record_training_video

    cfg = resolve_config("fetchreach-sacmc", {**SMALL, "total_steps": 200, "eval_every": 100, "video_every": 200})
    run = train(cfg, tmp_path / "v", progress=False, video=record_training_video)
    assert (run / "videos" / "eval_step200.mp4").stat().st_size > 10_000
    assert not (run / "videos" / "eval_step100.mp4").exists()
    acc = EventAccumulator(str(run), size_guidance={"images": 0})
    acc.Reload()
    images = acc.Images("eval/video")
    assert [im.step for im in images] == [200]
    assert images[0].encoded_image_string[:6] == b"GIF89a"
