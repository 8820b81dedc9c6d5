"""The MC module: closed-form KL, NLL fitting, and `mcrl measure` on a system with a known answer."""
import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from mcrl.cli import main
from mcrl.algo.mc import MCModels, gaussian_kl, gaussian_nll, transition_kl, MCOutputs


def test_kl_closed_form_matches_monte_carlo():
    rng = np.random.default_rng(0)
    mu_p, mu_q = rng.normal(size=3), rng.normal(size=3)
    ls_p, ls_q = rng.normal(scale=0.5, size=3), rng.normal(scale=0.5, size=3)
    x = mu_p + np.exp(ls_p) * rng.normal(size=(400_000, 3))
    log_ratio = (-np.asarray(gaussian_nll(x, mu_p, ls_p)) + np.asarray(gaussian_nll(x, mu_q, ls_q)))
    mc_estimate = log_ratio.mean(0)
    closed = np.asarray(gaussian_kl(mu_p, ls_p, mu_q, ls_q))
    se = log_ratio.std(0) / np.sqrt(len(x))
    assert np.all(np.abs(mc_estimate - closed) < 5 * se + 1e-4), (mc_estimate, closed)
    # KL of identical distributions is zero, and the per-transition value sums over dimensions
    out = MCOutputs(jnp.asarray(mu_p)[None], jnp.asarray(ls_p)[None], jnp.asarray(mu_q)[None], jnp.asarray(ls_q)[None])
    assert float(transition_kl(out)[0]) == pytest.approx(closed.sum(), rel=1e-5)
    assert float(gaussian_kl(mu_p, ls_p, mu_p, ls_p).sum()) == pytest.approx(0.0, abs=1e-6)


def _linear_gaussian(n, seed=0):
    """s' = A s + B a + noise; Var(s'_i | a) = (A Cov(s) A^T)_ii + noise_i^2."""
    rng = np.random.default_rng(seed)
    ds, da = 5, 3
    A = rng.normal(scale=0.5, size=(ds, ds))
    B = rng.normal(scale=0.8, size=(ds, da))
    noise = np.array([0.1, 0.2, 0.3, 0.15, 0.25])
    s = rng.normal(size=(n, ds))
    a = rng.uniform(-1, 1, size=(n, da))
    s2 = s @ A.T + a @ B.T + noise * rng.normal(size=(n, ds))
    var_given_a = np.diag(A @ A.T) + noise ** 2
    analytic_kl = 0.5 * np.sum(np.log(var_given_a / noise ** 2))
    return s.astype(np.float32), a.astype(np.float32), s2.astype(np.float32), A, B, noise, analytic_kl


def test_nll_models_recover_mean_and_std_of_linear_gaussian():
    s, a, s2, A, B, noise, _ = _linear_gaussian(20_000, seed=1)
    s, a, s2 = jnp.asarray(s), jnp.asarray(a), jnp.asarray(s2)
    models = MCModels(state_dim=5, hidden=(64, 64))
    params = models.init(jax.random.PRNGKey(0), 3)
    opt = optax.adam(2e-3)
    opt_state = opt.init(params)

    @jax.jit
    def step(params, opt_state, idx):
        (loss, _), g = jax.value_and_grad(models.loss, has_aux=True)(params, s[idx], a[idx], s2[idx])
        upd, opt_state = opt.update(g, opt_state, params)
        return optax.apply_updates(params, upd), opt_state

    rng = np.random.default_rng(0)
    for _ in range(4000):
        params, opt_state = step(params, opt_state, rng.integers(0, len(s), 256))
    st, at = np.asarray(s[:2000]), np.asarray(a[:2000])
    out = models.forward(params, st, at)
    mean_err = np.abs(np.asarray(out.mu_t) - (st @ A.T + at @ B.T)).mean(0)
    std = np.exp(np.asarray(out.log_std_t)).mean(0)
    assert np.all(mean_err < 0.1), mean_err
    np.testing.assert_allclose(std, noise, rtol=0.2)
    # the action-only model's variance includes the state's contribution
    std_a = np.exp(np.asarray(out.log_std_a)).mean(0)
    np.testing.assert_allclose(std_a, np.sqrt(np.diag(A @ A.T) + noise ** 2), rtol=0.2)


@pytest.mark.slow
def test_measure_cli_returns_analytic_kl(tmp_path, capsys):
    s, a, s2, *_, analytic = _linear_gaussian(40_000, seed=2)
    data = tmp_path / "lin.npz"
    np.savez(data, states=s, actions=a, next_states=s2)
    out = tmp_path / "kl.npy"
    rc = main(["measure", str(data), "--out", str(out), "--max-steps", "4000", "--hidden", "128", "128", "128", "--no-progress"])
    assert rc == 0
    text = capsys.readouterr().out
    measured = float(text.split("mean MC (KL per transition):")[1].split("nats")[0])
    assert measured == pytest.approx(analytic, rel=0.10), (measured, analytic)
    per = np.load(out)
    assert per.shape == (len(s),) and np.all(per >= 0)
