"""Gaussian-approximation filters for `jdrkf.NonlinearModel` (Wang 2022, Section III-A):
the unscented Kalman filter and the sampling ("ensemble") Gaussian filter."""

from __future__ import annotations

from collections.abc import Sequence
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
from jax.scipy.linalg import block_diag
from jaxtyping import Array, ArrayLike, Float, PRNGKeyArray

from .. import linalg
from .._gaussian import Gaussian, log_density
from .._nonlinear import NonlinearModel
from .._validation import is_concrete
from ._base import DEFAULT_OUTPUTS, RESULTS, AbstractFilter, StepOutput


_SIGMA_POINTS = ("merwe", "simon")


def merwe_weights(dim: int, alpha, beta, kappa, dtype) -> tuple[Float[Array, " N"], Float[Array, " N"]]:
    """Weights `(W^m, W^c)` of the `2 d + 1` scaled sigma points (Wan & van der Merwe;
    filterpy's `MerweScaledSigmaPoints`): `λ = α²(d + κ) − d`, `W^m_0 = λ/(d + λ)`,
    `W^c_0 = W^m_0 + 1 − α² + β`, `W_i = 1/(2(d + λ))`."""
    alpha, beta, kappa = (jnp.asarray(a, dtype) for a in (alpha, beta, kappa))
    lam = alpha**2 * (dim + kappa) - dim
    c = dim + lam  # d + λ, rounded as filterpy does (matters for small α)
    rest = jnp.full((2 * dim,), 0.5, dtype) / c
    wm = jnp.concatenate([(lam / c)[None], rest])
    wc = jnp.concatenate([(lam / c + 1.0 - alpha**2 + beta)[None], rest])
    return wm, wc


def sigma_points(
    mean: Float[Array, " d"], cov: Float[Array, "d d"], kind: str = "merwe", alpha=1.0, beta=2.0, kappa=0.0
) -> tuple[Float[Array, "N d"], Float[Array, " N"], Float[Array, " N"], Float[Array, ""]]:
    """Sigma points (rows) and weights `(points, W^m, W^c, ok)` of `N(mean, cov)`.

    - `"merwe"`: `χ_0 = m`, `χ_i, χ_{i+d} = m ± L_{:,i}` with `L = chol((d + λ) P)`
      (filterpy's `MerweScaledSigmaPoints`, same ordering).
    - `"simon"`: the `2 d` points `m ± L_{:,i}`, `L = chol(d P)`, weights `1/(2d)`
      (Simon 2006, eqs. (14.57)–(14.58); the authors' `UKF.m`).

    `ok` is `False` when the Cholesky factorization failed (`cov` not numerically
    positive definite); the points are then NaN.
    """
    d = mean.shape[-1]
    dtype = mean.dtype
    if kind == "merwe":
        wm, wc = merwe_weights(d, alpha, beta, kappa, dtype)
        scale = d + (jnp.asarray(alpha, dtype) ** 2 * (d + jnp.asarray(kappa, dtype)) - d)
    elif kind == "simon":
        wm = wc = jnp.full((2 * d,), 0.5 / d, dtype)
        scale = jnp.asarray(d, dtype)
    else:
        raise ValueError(f"sigma_points must be one of {_SIGMA_POINTS}, got {kind!r}")
    chol = linalg.cholesky(linalg.symmetrize(scale * cov))
    ok = jnp.all(jnp.isfinite(chol))
    spread = jnp.concatenate([chol.T, -chol.T])
    if kind == "merwe":
        spread = jnp.concatenate([jnp.zeros((1, d), dtype), spread])
    return mean + spread, wm, wc, ok


def _moments(points, wm):
    mean = wm @ points
    return mean, points - mean


def _weighted_outer(a, b, wc):
    return (a * wc[:, None]).T @ b


def _moment_update(pred_mean, pred_cov, dx, y_pred, dy, wc, noise_cov, y, observed):
    """Kalman-type update from the cross moments of prior state and measurement points
    (Wang 2022, Section III-A; Simon 2006, eqs. (14.64)–(14.67)):
    `P_yy = Σ W^c dy dyᵀ + R`, `P_xy = Σ W^c dx dyᵀ`, `K = P_xy P_yy⁻¹`,
    `m⁺ = m⁻ + K (y − ŷ)`, `P⁺ = P⁻ − K P_yy Kᵀ`. Entries of `y` that `observed` marks
    missing are decoupled (identity in `P_yy`, zero in `P_xy` and the innovation)."""
    pyy = _weighted_outer(dy, dy, wc) + noise_cov
    pxy = _weighted_outer(dx, dy, wc)
    innov = y - y_pred
    if observed is not None:
        obs_f = observed.astype(y.dtype)
        pyy = pyy * (obs_f[:, None] * obs_f[None, :]) + jnp.diag(1.0 - obs_f)
        pxy = pxy * obs_f[None, :]
        innov = jnp.where(observed, innov, 0.0)
        num_observed = jnp.sum(obs_f)
    else:
        num_observed = jnp.asarray(y.shape[0], y.dtype)
    pyy = linalg.symmetrize(pyy)
    chol_s = linalg.cholesky(pyy)
    failed = ~jnp.all(jnp.isfinite(chol_s))
    gain = linalg.cho_solve(chol_s, pxy.T).T
    mean = pred_mean + gain @ innov
    cov = linalg.symmetrize(pred_cov - gain @ pyy @ gain.T)
    loglik = log_density(chol_s, innov, num_observed)
    return Gaussian(mean, cov), loglik, failed


def _result(points_ok, failed, belief: Gaussian) -> RESULTS:
    finite = jnp.all(jnp.isfinite(belief.mean)) & jnp.all(jnp.isfinite(belief.cov)) & points_ok
    return RESULTS.where(
        failed & points_ok,
        RESULTS.nonpositive_innovation,
        RESULTS.where(finite, RESULTS.successful, RESULTS.nonfinite_state),
    )


def _ga_step(model: NonlinearModel, state: Gaussian, y, t, draw, redraw: bool, observed):
    """One Gaussian-approximation step with points from `draw(mean, cov) -> (points, W^m, W^c, ok)`.

    Additive noise: points of `N(m, P)` go through `f`; `P⁻ = Σ W^c dx dxᵀ + Q`. The
    measurement points are either redrawn from `N(m⁻, P⁻)` (`redraw=True`) or the
    propagated points themselves (`redraw=False`, so `P_xy`, `P_yy` omit `Q`).
    General noise: augmented points of `N([m; μ_w; μ_v], diag(P, Q, R))`; `x = f(x, w)`,
    and `y = h(x, v)` on the propagated points with their own `v` (`redraw=False`) or on
    points redrawn from `N([m⁻; μ_v], diag(P⁻, R))` (`redraw=True`).
    """
    n, q = model.state_dim, model.process_noise_dim
    mu_w, mu_v = model.process_mean, model.measurement_mean
    y = jnp.asarray(y, state.mean.dtype)
    if model.additive:
        chi, wm, wc, ok = draw(state.mean, state.cov)
        xp = jax.vmap(lambda x: model.f(x, t))(chi) + mu_w
        pred_mean, dx = _moments(xp, wm)
        pred_cov = linalg.symmetrize(_weighted_outer(dx, dx, wc) + model.Q)
        if redraw:
            xs, wm, wc, ok2 = draw(pred_mean, pred_cov)
            ok = ok & ok2
            dx = xs - pred_mean
        else:
            xs = xp
        ys = jax.vmap(lambda x: model.h(x, t))(xs) + mu_v
        noise_cov = model.R
    else:
        aug_mean = jnp.concatenate([state.mean, mu_w, mu_v])
        chi, wm, wc, ok = draw(aug_mean, block_diag(state.cov, model.Q, model.R))
        xp = jax.vmap(lambda x, w: model.f(x, w, t))(chi[:, :n], chi[:, n : n + q])
        pred_mean, dx = _moments(xp, wm)
        pred_cov = linalg.symmetrize(_weighted_outer(dx, dx, wc))
        if redraw:
            pts, wm, wc, ok2 = draw(jnp.concatenate([pred_mean, mu_v]), block_diag(pred_cov, model.R))
            ok = ok & ok2
            xs, vs = pts[:, :n], pts[:, n:]
            dx = xs - pred_mean
        else:
            xs, vs = xp, chi[:, n + q :]
        ys = jax.vmap(lambda x, v: model.h(x, v, t))(xs, vs)
        noise_cov = jnp.zeros((model.obs_dim, model.obs_dim), y.dtype)
    y_pred, dy = _moments(ys, wm)
    pred = Gaussian(pred_mean, pred_cov)
    filt, loglik, failed = _moment_update(pred_mean, pred_cov, dx, y_pred, dy, wc, noise_cov, y, observed)
    return filt, StepOutput(predicted=pred, filtered=filt, loglik=loglik, info=None, result=_result(ok, failed, filt))


def _check_prior(prior):
    if not isinstance(prior, Gaussian):
        raise ValueError(f"prior must be a jdrkf.Gaussian, got {type(prior).__name__}")


class UnscentedKF(AbstractFilter):
    r"""Unscented Kalman filter for `jdrkf.NonlinearModel` (Julier–Uhlmann; Wan & van der
    Merwe 2000; Simon 2006, pp. 448–450 — the Gaussian-approximation filter of Wang 2022,
    Section III-A and Corollary 1).

    **Arguments:**

    - `alpha`, `beta`, `kappa`: scaled sigma-point parameters (`sigma_points="merwe"`):
      `λ = α²(d + κ) − d`, weights as in filterpy's `MerweScaledSigmaPoints`; `d + λ > 0`
      is required. The defaults `α = 1, β = 2, κ = 0` (`λ = 0`, centre weight `W^m_0 = 0`,
      `W^c_0 = 2`) keep all mean weights nonnegative. The popular `α = 1e-3` gives
      `W^m_0 ≈ −1/α² = −10⁶` and outer weights `≈ +10⁶/(2d)`: the weighted means and
      covariances then cancel ~6 digits, which in float32 leaves ~1 significant digit
      and often a non-PSD covariance. Use small `α` only in float64.
    - `sigma_points`: `"merwe"` (`2d + 1` points) or `"simon"` (the `2d` points
      `m ± columns of chol(d P)`, equal weights `1/(2d)`: the authors' `UKF.m`, which
      is `"merwe"` with `κ = 0, α = 1, β = 0` up to the zero-weight centre point).
    - `redraw`: for the measurement update, draw new sigma points from the predicted
      `N(m⁻, P⁻)` (`True`, default: filterpy's `UnscentedKalmanFilter`) or reuse the
      propagated points (`False`: the authors' `UKF.m`). With additive noise the
      reused points do not carry `Q`, so `P_yy` and `P_xy` omit it and the filter is
      *not* the Kalman filter on a linear model; with `True` it is (exactly).
    - `throw`, `outputs`: as in `jdrkf.KalmanFilter`.

    Additive noise (`model.additive`): `d = n`, `Q` and `R` are added to the transformed
    covariances (with a `G`, put `G Q Gᵀ` in `Q`). General noise: the augmented UKF over
    `[x; w; v]` (`d = n + q + r`; `n + r` for the redrawn measurement points).

    Each step reports `RESULTS.nonfinite_state` if the Cholesky factor of a covariance
    to draw sigma points from fails (not positive definite, e.g. a singular prior or
    singular `Q` in the augmented form) and `RESULTS.nonpositive_innovation` if `P_yy`
    is not positive definite. The log-likelihood increment is
    `log N(y; ŷ, P_yy)` over the observed components.
    """

    alpha: float | Float[Array, ""]
    beta: float | Float[Array, ""]
    kappa: float | Float[Array, ""]
    sigma_points: str = eqx.field(static=True)
    redraw: bool = eqx.field(static=True)
    model_types: ClassVar[tuple[type, ...]] = (NonlinearModel,)

    def __init__(
        self,
        alpha: float | Float[ArrayLike, ""] = 1.0,
        beta: float | Float[ArrayLike, ""] = 2.0,
        kappa: float | Float[ArrayLike, ""] = 0.0,
        *,
        sigma_points: str = "merwe",
        redraw: bool = True,
        throw: bool = True,
        outputs: str | Sequence[str] = DEFAULT_OUTPUTS,
    ):
        if sigma_points not in _SIGMA_POINTS:
            raise ValueError(f"sigma_points must be one of {_SIGMA_POINTS}, got {sigma_points!r}")
        for name, value in (("alpha", alpha), ("beta", beta), ("kappa", kappa)):
            if jnp.ndim(value) != 0:
                raise ValueError(f"{name} must be a scalar, got shape {jnp.shape(value)}")
        if is_concrete(alpha) and not float(alpha) > 0.0:
            raise ValueError(f"alpha must be positive, got {float(alpha)}")
        self.alpha, self.beta, self.kappa = alpha, beta, kappa
        self.sigma_points, self.redraw = sigma_points, bool(redraw)
        self.throw, self.outputs = bool(throw), outputs

    def _dims(self, model: NonlinearModel) -> tuple[int, ...]:
        n, q, r = model.state_dim, model.process_noise_dim, model.measurement_noise_dim
        if model.additive:
            return (n,)
        return (n + q + r, n + r) if self.redraw else (n + q + r,)

    def init(self, model: NonlinearModel, prior: Gaussian) -> Gaussian:
        _check_prior(prior)
        if self.sigma_points == "merwe" and is_concrete(self.kappa):
            d = min(self._dims(model))
            if d + float(self.kappa) <= 0.0:
                raise ValueError(f"kappa={float(self.kappa)} gives d + λ = α²(d + κ) <= 0 for the sigma-point dimension d = {d}; need κ > −{d}")
        return prior

    def _draw(self, mean, cov):
        return sigma_points(mean, cov, self.sigma_points, self.alpha, self.beta, self.kappa)

    def step(self, model, state, y, t, u=None, key: PRNGKeyArray | None = None, observed=None):
        return _ga_step(model, state, y, t, self._draw, self.redraw, observed)


class EnsembleKF(AbstractFilter):
    r"""The sampling Gaussian-approximation filter of Wang 2022 ("GA-EnKF", the authors'
    `GaussianApproximation.m`): each step draws `N = num_samples` samples of
    `N(m, P)`, propagates them and applies the moment-matching update of
    `UnscentedKF` with equal weights `1/N` (sample covariances normalized by `N`,
    as in the authors' code).

    - `redraw=False` (default, the authors' code): the measurement samples are the
      propagated samples, so with additive noise `P_yy`, `P_xy` omit `Q` (as in
      `UnscentedKF(redraw=False)`); as `N → ∞` it tends to that filter's limit, not
      to the Kalman filter.
    - `redraw=True`: fresh samples of the predicted `N(m⁻, P⁻)` for the update; as
      `N → ∞` it tends to the Kalman filter on linear-Gaussian models.

    With general (non-additive) noise the samples are of `[x; w; v]` as in the
    augmented UKF. Stochastic: `step` needs a `key` (`__call__(model, prior, ys, key)`).
    """

    num_samples: int = eqx.field(static=True)
    redraw: bool = eqx.field(static=True)
    model_types: ClassVar[tuple[type, ...]] = (NonlinearModel,)

    def __init__(self, num_samples: int, *, redraw: bool = False, throw: bool = True, outputs: str | Sequence[str] = DEFAULT_OUTPUTS):
        if isinstance(num_samples, bool) or not isinstance(num_samples, int) or num_samples < 2:
            raise ValueError(f"num_samples must be an int >= 2, got {num_samples!r}")
        self.num_samples, self.redraw = num_samples, bool(redraw)
        self.throw, self.outputs = bool(throw), outputs

    def init(self, model: NonlinearModel, prior: Gaussian) -> Gaussian:
        _check_prior(prior)
        return prior

    def step(self, model, state, y, t, u=None, key: PRNGKeyArray | None = None, observed=None):
        if key is None:
            raise ValueError("EnsembleKF is stochastic: pass a PRNG key, e.g. filter(model, prior, ys, jax.random.key(0))")
        keys = iter(jax.random.split(key, 2))
        num = self.num_samples

        def draw(mean, cov):
            chol = linalg.cholesky(linalg.symmetrize(cov))
            z = jax.random.normal(next(keys), (num, mean.shape[-1]), mean.dtype)
            w = jnp.full((num,), 1.0 / num, mean.dtype)
            return mean + z @ chol.T, w, w, jnp.all(jnp.isfinite(chol))

        return _ga_step(model, state, y, t, draw, self.redraw, observed)
