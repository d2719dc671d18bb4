"""Gradients of Monte Carlo RMSE through whole filters (vs central finite differences),
and the optax / grid-search tuning helpers."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

import jdrkf
from jdrkf import tuning
from jdrkf.experiments import wang_ye
from jdrkf.sets import EpsContamination, Moment, Wasserstein


@pytest.fixture(scope="module")
def objective():
    train = wang_ye.scenario(jax.random.key(3), 3, 1.0, True, 60)
    return tuning.rmse_objective(wang_ye.nominal_model(), wang_ye.prior(), train)


CASES = {
    # name: (filter as a function of one scalar, point)
    "moment-theta2": (lambda x: jdrkf.DRKF(state_set=Moment(x), noise_set=Moment(1.02), outliers=EpsContamination(0.05, k=1.4)), 1.03),
    "wasserstein-theta_x": (lambda x: jdrkf.DRKF(state_set=Wasserstein(x), noise_set=Wasserstein(0.1), outliers=EpsContamination(0.05)), 0.2),
    "wasserstein-theta_v": (lambda x: jdrkf.DRKF(state_set=Wasserstein(0.2), noise_set=Wasserstein(x), outliers=EpsContamination(0.05)), 0.1),
    "eps": (lambda x: jdrkf.DRKF(state_set=Moment(1.02), noise_set=Moment(1.02), outliers=EpsContamination(x)), 0.05),
    "wkf-rho": (lambda x: jdrkf.WassersteinKF(x), 0.1),
    "huber-k": (lambda x: jdrkf.HuberKF(0.05, x), 1.4),
}


# wasserstein-theta_x covers the Wasserstein path in the default tier (suite time budget).
_SLOW_CASES = {"wasserstein-theta_v"}


@pytest.mark.parametrize("name", [pytest.param(n, marks=pytest.mark.slow) if n in _SLOW_CASES else n for n in sorted(CASES)])
def test_gradient_matches_finite_differences(objective, name):
    make, x0 = CASES[name]
    f = jax.jit(lambda x: objective(make(x)))
    grad = jax.grad(lambda x: objective(make(x)))(x0)
    h = 1e-5 * x0
    fd = (f(x0 + h) - f(x0 - h)) / (2 * h)
    assert abs(fd) > 1e-4  # the objective does depend on the parameter
    np.testing.assert_allclose(grad, fd, rtol=1e-5)


def test_fit_reduces_loss_and_respects_bounds(objective):
    mkf = wang_ye.mkf(1.08)
    where = lambda f: (f.state_set.theta2, f.noise_set.theta2)
    res = tuning.fit(mkf, objective, where=where, bounds=(1.0, None), shared=True, optimizer=optax.adam(0.1), steps=15)
    assert res.params.shape == (16, 1) and res.losses.shape == (16,)
    assert res.loss < 0.995 * res.losses[0]
    assert np.all(res.params >= 1.0)
    t2x, t2v = where(res.filter)
    assert float(t2x) == float(t2v) and float(t2x) < 1.08
    np.testing.assert_allclose(objective(res.filter), res.loss, rtol=1e-10)


def test_grid_search_finds_the_minimum_of_its_grid(objective):
    mkf = wang_ye.mkf()
    grid = np.array([1.0, 1.02, 1.05, 1.1])
    res = tuning.grid_search(mkf, objective, where=lambda f: (f.state_set.theta2, f.noise_set.theta2), grid=grid)
    direct = [float(objective(wang_ye.mkf(g))) for g in grid]
    np.testing.assert_allclose(res.losses, direct, rtol=1e-10)
    assert res.loss == min(res.losses) and res.loss == pytest.approx(min(direct), rel=1e-12)
    assert float(res.filter.state_set.theta2) == grid[int(np.argmin(direct))]


def test_grid_search_in_padded_chunks_reports_every_point(objective):
    """Chunks of 3 over 7 points (the last chunk padded): same losses as the direct
    evaluation, and the installed reporter sees all 7 points in one phase with a total."""
    from jdrkf import _progress

    grid = np.linspace(1.0, 1.12, 7)
    seen = []

    class Recorder:
        def phase(self, name, total=None, unit="it"):
            import contextlib

            @contextlib.contextmanager
            def cm():
                seen.append([name, total, 0])

                class P:
                    def update(self, n=1):
                        seen[-1][2] += n

                yield P()

            return cm()

    with _progress.reporting(Recorder()):
        res = tuning.grid_search(wang_ye.mkf(), objective, where=lambda f: (f.state_set.theta2, f.noise_set.theta2), grid=grid, chunk_size=3)
    direct = [float(objective(wang_ye.mkf(g))) for g in grid]
    np.testing.assert_allclose(res.losses, direct, rtol=1e-10)
    assert res.losses.shape == (7,)
    assert seen == [["grid search (7 points)", 7, 7]]
    with pytest.raises(ValueError, match="chunk_size"):
        tuning.grid_search(wang_ye.mkf(), objective, where=lambda f: f.state_set.theta2, grid=grid, chunk_size=0)


def test_sigmoid_bounds_and_bad_arguments(objective):
    flt = jdrkf.DRKF(state_set=Moment(1.02), noise_set=Moment(1.02), outliers=EpsContamination(0.05))
    res = tuning.fit(flt, objective, where=lambda f: f.outliers.eps, bounds=(0.0, 0.5), steps=3)
    assert np.all((res.params > 0) & (res.params < 0.5))
    with pytest.raises(ValueError, match="bounds"):
        tuning.fit(flt, objective, where=lambda f: f.outliers.eps, bounds=(0.5, 0.1), steps=1)
    with pytest.raises(ValueError, match="where"):
        tuning.fit(jdrkf.HuberKF(0.05, 1.4), objective, where=lambda f: f.outliers.k.shape, steps=1)
    with pytest.raises(ValueError, match="grid"):
        tuning.grid_search(flt, objective, where=lambda f: (f.state_set.theta2, f.noise_set.theta2), grid=np.ones((3, 3)))


def test_objective_is_jittable_as_a_function_of_the_filter(objective):
    flt = wang_ye.mkf()
    np.testing.assert_allclose(eqx.filter_jit(objective)(flt), objective(flt), rtol=1e-12)


# --------------------------------------------------------------------------- fit's options
# Toy objectives of a filter's leaves with closed-form minima: cheap, and independent of the filters.

HUBER_WHERE = lambda f: (f.outliers.eps, f.outliers.k)
HUBER_BOUNDS = [(0.0, 0.5), (0.0, None)]


def _quadratic(f):
    return 1.0 + (f.outliers.k - 2.0) ** 2 + 3.0 * (f.outliers.eps - 0.2) ** 2  # minimum 1 at (eps, k) = (0.2, 2)


def _streaks(losses, params, tol):
    """NumPy re-implementation of the convergence test: length of the run of small relative changes at each step."""
    out, streak = [], 0
    for i in range(len(losses)):
        small = i > 0 and abs(losses[i] - losses[i - 1]) <= tol * abs(losses[i - 1]) and np.all(np.abs(params[i] - params[i - 1]) <= tol * np.abs(params[i - 1]))
        streak = streak + 1 if small else 0
        out.append(streak)
    return out


def test_fit_convergence_test_stops_at_the_first_small_streak():
    flt, tol, patience = jdrkf.HuberKF(0.05, 1.4), 1e-3, 2
    res = tuning.fit(flt, _quadratic, where=HUBER_WHERE, bounds=HUBER_BOUNDS, optimizer=optax.adam(0.1), steps=500, tol=tol, patience=patience)
    streaks = _streaks(res.losses, res.params, tol)
    assert res.converged and len(res.losses) < 501
    assert streaks[-1] == patience and max(streaks[:-1]) < patience  # stopped exactly at the first streak of `patience`
    np.testing.assert_allclose(res.params[res.best_step], [0.2, 2.0], atol=0.05)
    # Running out of steps: converged is False and every step is recorded (plus the iterate after the last).
    short = tuning.fit(flt, _quadratic, where=HUBER_WHERE, bounds=HUBER_BOUNDS, steps=5, tol=1e-12)
    assert not short.converged and short.losses.shape == (6,) and short.params.shape == (6, 2)
    assert not tuning.fit(flt, _quadratic, where=HUBER_WHERE, bounds=HUBER_BOUNDS, steps=5).converged  # tol=None: no test


def test_fit_returns_the_best_iterate_not_the_last():
    flt = jdrkf.HuberKF(0.05, 1.4)
    res = tuning.fit(flt, _quadratic, where=HUBER_WHERE, bounds=HUBER_BOUNDS, optimizer=optax.adam(1.0), steps=12)
    assert res.losses[-1] > res.loss  # the large step size overshoots: the last iterate is worse
    assert res.best_step == int(np.argmin(res.losses)) and res.loss == res.losses.min()
    np.testing.assert_allclose([float(x) for x in HUBER_WHERE(res.filter)], res.params[res.best_step], rtol=1e-12)
    np.testing.assert_allclose(float(_quadratic(res.filter)), res.loss, rtol=1e-12)


def _double_well(f):
    k = f.outliers.k
    return (k - 1.0) ** 2 * (k - 3.0) ** 2 + 0.5 * (k - 3.0) ** 2 / (1 + (k - 3.0) ** 2)  # local minimum near 1, global at 3


def test_fit_restarts_escape_a_local_minimum_and_keep_every_history():
    flt = jdrkf.HuberKF(0.05, 0.7)
    where = lambda f: f.outliers.k
    single = tuning.fit(flt, _double_well, where=where, optimizer=optax.adam(0.05), steps=150)
    assert abs(single.params[single.best_step, 0] - 1.0) < 0.1  # stuck in the local minimum
    res = tuning.fit(flt, _double_well, where=where, optimizer=optax.adam(0.05), steps=150, restarts=5, jitter=1.5, key=jax.random.key(0))
    assert len(res.runs) == 6
    np.testing.assert_allclose(res.runs[0].params[0], [0.7], rtol=1e-12)  # start 0 = the filter's own value
    np.testing.assert_array_equal(res.runs[0].losses, single.losses)
    assert len({float(r.params[0, 0]) for r in res.runs}) == 6  # jittered starts
    bests = [r.losses[r.best_step] for r in res.runs]
    assert res.start == int(np.argmin(bests)) and res.loss == min(bests)
    np.testing.assert_array_equal(res.losses, res.runs[res.start].losses)
    assert abs(float(res.filter.outliers.k) - 3.0) < 0.05 and res.loss < 1e-3


@pytest.mark.parametrize("tol", [None, 1e-3])
def test_fit_in_lax_scan_matches_the_python_loop(tol):
    flt = jdrkf.HuberKF(0.05, 1.4)
    kw = {"where": HUBER_WHERE, "bounds": HUBER_BOUNDS, "optimizer": optax.adam(0.1), "steps": 200, "tol": tol, "restarts": 2}
    loop, scanned = tuning.fit(flt, _quadratic, **kw), tuning.fit(flt, _quadratic, scan=True, **kw)
    assert loop.converged == scanned.converged == (tol is not None)
    for a, b in zip(loop.runs, scanned.runs, strict=True):
        np.testing.assert_allclose(a.losses, b.losses, rtol=1e-12, atol=1e-300)
        np.testing.assert_allclose(a.params, b.params, rtol=1e-12)
        assert (a.best_step, a.converged) == (b.best_step, b.converged)


def test_fit_in_lax_scan_through_a_dr_filter(objective):
    kw = {"where": lambda f: (f.state_set.theta2, f.noise_set.theta2), "bounds": (1.0, None), "shared": True, "optimizer": optax.adam(0.1), "steps": 3}
    loop, scanned = tuning.fit(wang_ye.mkf(1.08), objective, **kw), tuning.fit(wang_ye.mkf(1.08), objective, scan=True, **kw)
    np.testing.assert_allclose(scanned.losses, loop.losses, rtol=1e-10)
    np.testing.assert_allclose(scanned.params, loop.params, rtol=1e-10)


def test_fit_progress_callback_and_bar(capsys):
    flt, seen = jdrkf.HuberKF(0.05, 1.4), []
    res = tuning.fit(flt, _quadratic, where=HUBER_WHERE, bounds=HUBER_BOUNDS, steps=4, restarts=1,
                     progress=lambda s, i, loss, p: seen.append((s, i, loss, np.array(p))))
    assert [(s, i) for s, i, _, _ in seen] == [(0, 0), (0, 1), (0, 2), (0, 3), (1, 0), (1, 1), (1, 2), (1, 3)]
    for s, i, loss, p in seen:
        assert loss == res.runs[s].losses[i]
        np.testing.assert_array_equal(p, res.runs[s].params[i])
    tuning.fit(flt, _quadratic, where=HUBER_WHERE, bounds=HUBER_BOUNDS, steps=3, progress=True)
    assert "3/3" in capsys.readouterr().err  # tqdm's bar on stderr
    with pytest.raises(ValueError, match="progress"):
        tuning.fit(flt, _quadratic, where=HUBER_WHERE, bounds=HUBER_BOUNDS, steps=3, progress=True, scan=True)
    with pytest.raises(ValueError, match="progress"):
        tuning.fit(flt, _quadratic, where=HUBER_WHERE, bounds=HUBER_BOUNDS, steps=3, progress="yes")


def test_bounds_are_never_reached_in_float32():
    # The raw maps saturate in float32: sigmoid rounds to 1 and softplus vanishes next to the bound.
    assert float(0.5 * jax.nn.sigmoid(jnp.float32(20.0))) == 0.5 and float(1.0 + jax.nn.softplus(jnp.float32(-20.0))) == 1.0
    u = jnp.asarray([-1e30, -1e4, -100.0, -20.0, 0.0, 20.0, 100.0, 1e4, 1e30], jnp.float32)
    for lower, upper in [(0.0, 0.5), (1.0, None), (0.0, 0.1), (0.1, None), (-0.3, 0.7)]:
        x = np.asarray(jax.vmap(tuning._Bounds(lower, upper).to)(u), np.float64)
        assert x.dtype == np.float64 and np.all(x > lower) and (upper is None or np.all(x < upper)), (lower, upper, x)
    # Through fit: an objective that pushes ε to its upper bound and k to its lower bound, with huge steps.
    flt = jdrkf.HuberKF(0.05, 1.4)
    flt = eqx.tree_at(HUBER_WHERE, flt, (jnp.float32(0.05), jnp.float32(1.4)))
    res = tuning.fit(flt, lambda f: f.outliers.k - f.outliers.eps, where=HUBER_WHERE, bounds=[(0.0, 0.5), (1.0, None)],
                     optimizer=optax.sgd(1e4), steps=5)
    eps, k = HUBER_WHERE(res.filter)
    assert eps.dtype == jnp.float32 and k.dtype == jnp.float32
    assert 0.49 < float(eps) < 0.5 and 1.0 < float(k) < 1.01
    assert np.all(res.params[:, 0] < 0.5) and np.all(res.params[:, 1] > 1.0)


def test_fit_rejects_bad_arguments():
    flt = jdrkf.HuberKF(0.05, 1.4)
    kw = {"where": HUBER_WHERE, "bounds": HUBER_BOUNDS}
    for bad, match in [({"steps": 0}, "steps"), ({"steps": 2.5}, "steps"), ({"steps": True}, "steps"), ({"tol": 0.0}, "tol"),
                       ({"tol": -1e-3}, "tol"), ({"tol": float("nan")}, "tol"), ({"patience": 0}, "patience"),
                       ({"restarts": -1}, "restarts"), ({"restarts": 1.5}, "restarts"), ({"jitter": -1.0}, "jitter"),
                       ({"mode": "sideways"}, "mode")]:
        with pytest.raises(ValueError, match=match):
            tuning.fit(flt, _quadratic, **kw, **bad)
    with pytest.raises(ValueError, match="outside its bounds"):
        tuning.fit(flt, _quadratic, where=HUBER_WHERE, bounds=[(0.0, 0.01), (0.0, None)], steps=1)


def test_forward_mode_gives_the_reverse_mode_derivative_through_a_filter(objective):
    """`value_and_grad(mode="forward")` (jax.jacfwd) against reverse mode and central
    differences, through the Huber KF's two parameters (a pytree argument)."""
    f = lambda x: objective(jdrkf.HuberKF(x[0], x[1]))
    x = (jnp.asarray(0.05), jnp.asarray(1.4))
    (v_r, g_r), (v_f, g_f) = (jax.jit(tuning.value_and_grad(f, mode=m))(x) for m in ("reverse", "forward"))
    np.testing.assert_allclose(v_f, v_r, rtol=1e-14)
    np.testing.assert_allclose(np.asarray(g_f), np.asarray(g_r), rtol=1e-9)
    fd = _central_difference(lambda v: f((v[0], v[1])), np.asarray([0.05, 1.4]), 1)
    np.testing.assert_allclose(float(g_f[1]), fd, rtol=1e-5)
    with pytest.raises(ValueError, match="mode"):
        tuning.value_and_grad(f, mode="sideways")


def test_fit_in_forward_mode_takes_the_same_steps():
    kw = {"where": HUBER_WHERE, "bounds": HUBER_BOUNDS, "optimizer": optax.adam(0.1), "steps": 30}
    rev, fwd = (tuning.fit(jdrkf.HuberKF(0.05, 1.4), _quadratic, mode=m, **kw) for m in ("reverse", "forward"))
    np.testing.assert_allclose(fwd.losses, rev.losses, rtol=1e-12)
    np.testing.assert_allclose(fwd.params, rev.params, rtol=1e-12)
    assert fwd.best_step == rev.best_step and fwd.loss < 1.01 < fwd.losses[0]  # the minimum is 1


# --------------------------------------------------------------------------- gradients through several DR filters' tuned parameters


def _central_difference(f, x, i, rel=1e-5):
    h = rel * x[i]
    up, dn = np.array(x), np.array(x)
    up[i] += h
    dn[i] -= h
    return (float(f(up)) - float(f(dn))) / (2 * h)


def _check_gradient(f, x, components=None):
    grad = np.asarray(jax.grad(f)(jnp.asarray(x)))
    jf = jax.jit(f)
    for i in range(len(x)) if components is None else components:
        fd = _central_difference(jf, x, i)
        assert abs(fd) > 1e-6  # the objective depends on every tuned parameter
        np.testing.assert_allclose(grad[i], fd, rtol=1e-5)


@pytest.mark.slow  # ~16 s; the steady-state gradient is also checked in tests/test_wasserstein_dr.py
def test_gradient_through_steady_state_drkf_radii(objective):
    _check_gradient(lambda v: objective(jdrkf.SteadyStateDRKF(v[0], v[1])), [0.3, 0.2])


@pytest.mark.slow  # ~20 s; chen-fusion's per-sensor KL radii are also checked by the tuning-problem test below
@pytest.mark.parametrize("sensor", [0, 1, 2])
def test_gradient_through_marginal_drkf_per_sensor_radii(sensor):
    from jdrkf.experiments import chen_fusion
    from jdrkf.sets import MarginalKL

    model, true, prior = chen_fusion.scenario("paper")
    tr = jdrkf.simulate(jax.random.key(5), true, jdrkf.Gaussian(jnp.zeros(3), jnp.zeros((3, 3))), 40, 3)

    def f(c):
        means = jax.vmap(lambda y: jdrkf.MarginalDRKF(MarginalKL(c))(model, prior, y).filtered_means)(tr.observations)
        return jnp.mean(jnp.sum((tr.states - means) ** 2, axis=-1))

    _check_gradient(f, [0.05, 0.1, 0.02], components=[sensor])


def test_gradient_through_wasserstein_drkf_three_parameters(objective):
    _check_gradient(lambda v: objective(jdrkf.DRKF(state_set=Wasserstein(v[0]), noise_set=Wasserstein(v[1]), outliers=EpsContamination(v[2]))), [0.2, 0.1, 0.05])


# --------------------------------------------------------------------------- the experiments' tuning problems
def _problems():
    """(experiment, filter) of every registered tuning problem except the particle filter's
    (its objective is piecewise constant in the resampling: finite differences do not
    apply; its gradient is checked against the Kalman filter's exact score in
    tests/test_resampling.py)."""
    import jdrkf.experiments as ex

    seen, out = set(), []
    for name, exp in sorted(ex.EXPERIMENTS.items()):
        if exp.tuning is None or exp.tuning in seen:
            continue
        seen.add(exp.tuning)
        out += [(name, label) for label, problem in exp.tuning(True).items() if name != "wang-growth"]
    return out


@pytest.mark.slow  # one compilation of value-and-gradient per problem
@pytest.mark.parametrize("experiment,label", _problems())
def test_gradient_through_every_tuned_parameter_matches_finite_differences(experiment, label):
    """Every parameter of every experiment's tuning problem (quick data, 3 runs), at its
    start: the gradient of the training objective vs central finite differences (1e-5)."""
    import jdrkf.experiments as ex

    problem = ex.EXPERIMENTS[experiment].tuning(True)[label]
    data = problem.data(jax.random.key(0), 3)
    start = tuple(jnp.asarray(float(x)) for x in problem.start)
    loss = jax.jit(problem.loss)
    grad = jax.grad(problem.loss)(start, data)
    for i, x in enumerate(problem.start):
        h = 1e-5 * max(abs(float(x)), 1e-2)
        up = tuple(jnp.asarray(float(v) + (h if j == i else 0.0)) for j, v in enumerate(problem.start))
        down = tuple(jnp.asarray(float(v) - (h if j == i else 0.0)) for j, v in enumerate(problem.start))
        fd = (float(loss(up, data)) - float(loss(down, data))) / (2 * h)
        assert abs(fd) > 1e-8, f"{problem.names[i]}: the objective does not depend on it"
        np.testing.assert_allclose(float(grad[i]), fd, rtol=1e-5, atol=1e-9, err_msg=problem.names[i])
