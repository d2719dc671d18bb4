"""Linear state-space models with optional time variation and control inputs."""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from ._gaussian import Gaussian
from ._validation import as_float_array, check_covariance, check_shape, check_time_axis, is_concrete


_BASE_NDIM = {"F": 2, "H": 2, "Q": 2, "R": 2, "G": 2, "B": 2, "process_mean": 1, "noise_mean": 1}


class LinearModel(eqx.Module):
    r"""Linear state-space model (time convention: `prior` is the law of `x_0`).

    For `k = 1..T` (array index `t = k − 1`):

    $$x_k = F_t x_{k-1} + B_t u_t + G_t w_t,\quad w_t \sim (\mu_{w,t}, Q_t)$$

    $$y_k = H_t x_k + v_t,\quad v_t \sim (\mu_{v,t}, R_t)$$

    **Arguments:**

    - `F`: `(n, n)` transition matrix.
    - `H`: `(m, n)` observation matrix.
    - `Q`: `(q, q)` process-noise covariance.
    - `R`: `(m, m)` measurement-noise covariance.
    - `G`: `(n, q)` noise input matrix; default identity (`q = n`).
    - `B`: `(n, p)` control matrix multiplying `inputs[t]`; default none.
    - `process_mean`: `(q,)` mean of `w`; default zero.
    - `noise_mean`: `(m,)` mean of `v`; default zero.

    Any field may carry a leading time axis of length `T` (a time-varying system);
    all time-varying fields must agree on `T`. `model.at(t)` returns the step-`t`
    matrices. Integer inputs are promoted to the default float dtype; all fields
    share one dtype.
    """

    F: Float[Array, "*T n n"]
    H: Float[Array, "*T m n"]
    Q: Float[Array, "*T q q"]
    R: Float[Array, "*T m m"]
    G: Float[Array, "*T n q"]
    B: Float[Array, "*T n p"] | None
    process_mean: Float[Array, "*T q"]
    noise_mean: Float[Array, "*T m"]

    def __init__(
        self,
        F: Float[ArrayLike, "*T n n"],
        H: Float[ArrayLike, "*T m n"],
        Q: Float[ArrayLike, "*T q q"],
        R: Float[ArrayLike, "*T m m"],
        G: Float[ArrayLike, "*T n q"] | None = None,
        B: Float[ArrayLike, "*T n p"] | None = None,
        process_mean: Float[ArrayLike, "*T q"] | None = None,
        noise_mean: Float[ArrayLike, "*T m"] | None = None,
    ):
        F = as_float_array("F", F, (2, 3))
        H = as_float_array("H", H, (2, 3))
        Q = as_float_array("Q", Q, (2, 3))
        R = as_float_array("R", R, (2, 3))
        n = F.shape[-1]
        check_shape("F", F, (n, n), "(F must be square)")
        m = H.shape[-2]
        check_shape("H", H, (m, n), f"since the state dimension is {n}")
        check_covariance("Q", Q)
        check_covariance("R", R)
        check_shape("R", R, (m, m), f"since H has {m} rows")
        q = Q.shape[-1]
        if G is None:
            if q != n:
                raise ValueError(f"Q has shape {tuple(Q.shape)} but the state dimension is {n}; pass G of shape ({n}, {q})")
            G = jnp.eye(n, dtype=F.dtype)
        G = as_float_array("G", G, (2, 3))
        check_shape("G", G, (n, q), f"since the state dimension is {n} and Q is {q}x{q}")
        if B is not None:
            B = as_float_array("B", B, (2, 3))
            check_shape("B", B, (n, None), f"since the state dimension is {n}")
        process_mean = jnp.zeros(q, F.dtype) if process_mean is None else as_float_array("process_mean", process_mean, (1, 2))
        check_shape("process_mean", process_mean, (q,), f"to match Q ({q}x{q})")
        noise_mean = jnp.zeros(m, F.dtype) if noise_mean is None else as_float_array("noise_mean", noise_mean, (1, 2))
        check_shape("noise_mean", noise_mean, (m,), f"to match R ({m}x{m})")

        fields = dict(F=F, H=H, Q=Q, R=R, G=G, B=B, process_mean=process_mean, noise_mean=noise_mean)
        num_steps = None
        for name, value in fields.items():
            if value is not None:
                num_steps = check_time_axis(name, value, _BASE_NDIM[name], num_steps)
        dtype = jnp.result_type(*[v for v in fields.values() if v is not None])
        for name, value in fields.items():
            setattr(self, name, None if value is None else value.astype(dtype))

    @property
    def state_dim(self) -> int:
        return self.F.shape[-1]

    @property
    def obs_dim(self) -> int:
        return self.H.shape[-2]

    @property
    def num_steps(self) -> int | None:
        """Length of the time axis, or `None` for a time-invariant model."""
        for name, base in _BASE_NDIM.items():
            value = getattr(self, name)
            if value is not None and value.ndim == base + 1:
                return value.shape[0]
        return None

    def at(self, t: Int[ArrayLike, ""]) -> "LinearModel":
        """The model of step `t` (0-based array index, i.e. step `k = t + 1`).

        Time-invariant fields are returned as they are; indexing is a `dynamic_index`,
        so `t` may be traced (as inside `lax.scan`).
        """
        names = [k for k, base in _BASE_NDIM.items() if getattr(self, k) is not None and getattr(self, k).ndim == base + 1]
        if not names:
            return self
        return eqx.tree_at(lambda mdl: [getattr(mdl, k) for k in names], self, [getattr(self, k)[t] for k in names])

    def check_inputs(self, inputs, num_steps: int) -> None:
        """Eager check of a control sequence against `B` and the horizon."""
        if self.B is None:
            if inputs is not None:
                raise ValueError("inputs were given but the model has no control matrix B")
            return
        if inputs is None:
            raise ValueError(f"the model has a control matrix B of shape {tuple(self.B.shape)} but no inputs were given")
        p = self.B.shape[-1]
        if inputs.ndim != 2 or inputs.shape != (num_steps, p):
            raise ValueError(f"inputs has shape {tuple(inputs.shape)} but expected ({num_steps}, {p}) (T steps, B has {p} columns)")

    @classmethod
    def from_dynamax(cls, params, num_timesteps: int | None = None) -> tuple[LinearModel, Gaussian]:
        r"""Convert dynamax's `ParamsLGSSM` into a model and the prior of `x_0`.

        dynamax conditions its first state on the first observation: `params.initial` is
        the law of the state that `emissions[0]` observes, and the dynamics entry `t ≥ 1`
        maps that index-`(t−1)` state to index `t` (entry 0 is never used). jdrkf predicts
        before every update. The conversion therefore makes the first step the identity,
        `x_1 = x_0` (`F_0 = I`, `Q_0 = 0`, no bias or input), and returns `params.initial`
        as the law of `x_0`; steps `t ≥ 1` carry dynamax's entries `t`. Then `x_{t+1}` is
        dynamax's state `t`, the same `ys` and `inputs` arrays feed both libraries, and
        `KalmanFilter()(model, prior, ys)` gives `lgssm_filter(params, ys)`'s filtered
        means and marginal log-likelihood. `F, Q, process_mean` (and `B`) get a time axis
        of length `num_timesteps` even for time-invariant `params`; `model.at(1)` is then
        dynamax's time-invariant model, to be started from `update(model.at(1), prior, ys[0], 0)`
        on `ys[1:]` (and `inputs[1:]`).

        Mapping: `F = weights`, `G = I`, `Q = cov`, `process_mean = bias`,
        `B = input_weights` (none when it has no columns), `H, R` as given (a diagonal
        `cov` of shape `(m,)` or `(T, m)` becomes `diag(cov)`), `noise_mean = bias`.
        jdrkf has no input term in the measurement equation, so `params.emissions.input_weights`
        must be zero.

        **Arguments:**

        - `params`: a dynamax `ParamsLGSSM` (or any object with its fields) holding arrays.
        - `num_timesteps`: the number of observations `T`; required when no field of
          `params` has a time axis, else it must match that axis.

        **Returns:** `(model, prior)`.
        """
        try:
            init, dyn, emi = params.initial, params.dynamics, params.emissions
        except AttributeError as e:
            raise ValueError(f"params must be a dynamax ParamsLGSSM, got {type(params).__name__}") from e
        mean = as_float_array("params.initial.mean", init.mean, (1,))
        cov = as_float_array("params.initial.cov", init.cov, (2,))
        F = as_float_array("params.dynamics.weights", dyn.weights, (2, 3))
        b = as_float_array("params.dynamics.bias", dyn.bias, (1, 2))
        B = as_float_array("params.dynamics.input_weights", dyn.input_weights, (2, 3))
        Q = as_float_array("params.dynamics.cov", dyn.cov, (2, 3))
        H = as_float_array("params.emissions.weights", emi.weights, (2, 3))
        d = as_float_array("params.emissions.bias", emi.bias, (1, 2))
        D = as_float_array("params.emissions.input_weights", emi.input_weights, (2, 3))
        R = as_float_array("params.emissions.cov", emi.cov, (1, 2, 3))
        if R.ndim == 1 or (R.ndim == 2 and R.shape[0] != R.shape[1]):  # dynamax's diagonal forms
            R = R[..., None, :] * jnp.eye(R.shape[-1], dtype=R.dtype)
        if D.size and not (is_concrete(D) and not jnp.any(D)):
            raise ValueError(
                "params.emissions.input_weights must be zero: jdrkf models have no input term in the "
                "measurement equation"
            )
        steps = None
        for name, x, base in (("dynamics.weights", F, 2), ("dynamics.bias", b, 1), ("dynamics.input_weights", B, 2),
                              ("dynamics.cov", Q, 2), ("emissions.weights", H, 2), ("emissions.bias", d, 1),
                              ("emissions.cov", R, 2)):
            steps = check_time_axis("params." + name, x, base, steps)
        if num_timesteps is None:
            if steps is None:
                raise ValueError("num_timesteps is required: no field of params has a time axis")
            num_timesteps = steps
        elif steps is not None and num_timesteps != steps:
            raise ValueError(f"num_timesteps is {num_timesteps} but the time-varying fields of params have length {steps}")
        if num_timesteps < 1:
            raise ValueError(f"num_timesteps must be at least 1, got {num_timesteps}")

        def first_step(x, base, value):
            x = x if x.ndim == base + 1 else jnp.broadcast_to(x, (num_timesteps,) + x.shape)
            return x.at[0].set(value)

        model = cls(
            F=first_step(F, 2, jnp.eye(F.shape[-1], dtype=F.dtype)),
            H=H,
            Q=first_step(Q, 2, 0.0),
            R=R,
            B=first_step(B, 2, 0.0) if B.shape[-1] else None,
            process_mean=first_step(b, 1, 0.0),
            noise_mean=d,
        )
        return model, Gaussian(mean, cov)

    def to_dynamax(self, prior: Gaussian, inputs: Float[ArrayLike, "T p"] | None = None):
        r"""Convert to dynamax's `ParamsLGSSM` (needs dynamax: `pip install 'jdrkf[bench]'`).

        The inverse time shift of `from_dynamax`: dynamax's initial law is that of `x_1`
        before `y_1`, the prediction of `prior` through step 0,
        `μ_1 = F_0 m_0 + B_0 u_1 + G_0 μ_{w,0}`, `Σ_1 = F_0 P_0 F_0ᵀ + G_0 Q_0 G_0ᵀ`; dynamax
        ignores dynamics entry 0 and reads entry `t ≥ 1` for `x_t → x_{t+1}`, as jdrkf does.
        Dynamics: `weights = F`, `bias = G μ_w`, `cov = G Q Gᵀ`, `input_weights = B` (or
        `n × 0`); emissions: `weights = H`, `bias = noise_mean`, `cov = R`, zero input
        weights. `lgssm_filter(params, ys, inputs)` then filters like jdrkf's `KalmanFilter`
        on `(model, prior, ys, inputs=inputs)`. Time-varying fields stay time-varying.

        **Arguments:**

        - `prior`: the law of `x_0`.
        - `inputs`: `(T, p)`, the control sequence when the model has `B` (its first row
          enters `μ_1`); otherwise `None`.
        """
        try:
            from dynamax.linear_gaussian_ssm import ParamsLGSSM, ParamsLGSSMDynamics, ParamsLGSSMEmissions, ParamsLGSSMInitial
        except ImportError as e:
            raise ImportError("LinearModel.to_dynamax needs dynamax: pip install 'jdrkf[bench]' (or pip install dynamax)") from e
        from .filters._kalman import predict

        if not isinstance(prior, Gaussian) or prior.dim != self.state_dim:
            raise ValueError(f"prior must be a Gaussian of dimension {self.state_dim}, got {prior!r}")
        u1 = None
        if self.B is None:
            if inputs is not None:
                raise ValueError("inputs were given but the model has no control matrix B")
        else:
            if inputs is None:
                raise ValueError(f"the model has a control matrix B of shape {tuple(self.B.shape)} but no inputs were given")
            inputs = as_float_array("inputs", inputs, (2,))
            check_shape("inputs", inputs, (None, self.B.shape[-1]), f"since B has {self.B.shape[-1]} columns")
            u1 = inputs[0]
        first = predict(self, prior, 0, u1)
        p = 0 if self.B is None else self.B.shape[-1]
        dtype = self.F.dtype
        return ParamsLGSSM(
            initial=ParamsLGSSMInitial(mean=first.mean, cov=first.cov),
            dynamics=ParamsLGSSMDynamics(
                weights=self.F,
                bias=(self.G @ self.process_mean[..., None])[..., 0],
                input_weights=jnp.zeros((self.state_dim, 0), dtype) if self.B is None else self.B,
                cov=self.G @ self.Q @ jnp.swapaxes(self.G, -1, -2),
            ),
            emissions=ParamsLGSSMEmissions(
                weights=self.H, bias=self.noise_mean, input_weights=jnp.zeros((self.obs_dim, p), dtype), cov=self.R
            ),
        )

    def to_cuthbert(
        self,
        prior: Gaussian,
        ys: Float[ArrayLike, "T m"],
        inputs: Float[ArrayLike, "T p"] | None = None,
        observed: Bool[ArrayLike, "T m"] | None = None,
    ):
        r"""cuthbert's exact (square-root) Kalman filter for this model and its model inputs
        (needs cuthbert: `pip install cuthbert`).

        cuthbert indexes time as jdrkf does: `m0, chol_P0` describe `x_0`, and model input
        `t` carries the transition `x_t → x_{t+1}` and the observation `y_{t+1} = ys[t]`,
        so no shift is needed. Per step, from `model.at(t)`:
        `p(x_{t+1} | x_t) = N(F x_t + c, L_Q L_Qᵀ)` with `c = B u_t + G μ_w` and `L_Q` the
        triangularization of `G S_Q` (`S_Q S_Qᵀ = Q`), so `L_Q L_Qᵀ = G Q Gᵀ` even for a
        singular `Q` or `q ≠ n`; `p(y | x) = N(H x + μ_v, S_R S_Rᵀ)`; `chol_P0` is the
        factor of `prior.cov`. Entries that `observed` marks missing become NaN, cuthbert's
        missing-data marker. `cuthbert.filter(kf, model_inputs, kf.init_prepare())` then
        returns `T + 1` states, the first one `x_0`'s: drop it to get the filtered means,
        covariances `chol_cov @ chol_covᵀ` and the cumulative log-likelihood of
        `KalmanFilter()(model, prior, ys, inputs=inputs, observed=observed)`. With
        `parallel=True` (cuthbert's associative scan) the log-likelihood needs `G Q Gᵀ`
        nonsingular; the means and covariances do not.

        **Arguments:**

        - `prior`: the law of `x_0`.
        - `ys`: `(T, m)` observations, `ys[t] = y_{t+1}`.
        - `inputs`: `(T, p)` controls when the model has `B`; otherwise `None`.
        - `observed`: boolean mask of the shape of `ys` (`None`: every entry is used).

        **Returns:** `(kf, model_inputs)`: the `cuthbert.Filter` of
        `cuthbert.gaussian.kalman.build_filter` and a dict of arrays with leading axis `T`.
        """
        try:
            from cuthbert.gaussian import kalman
        except ImportError as e:
            raise ImportError("LinearModel.to_cuthbert needs cuthbert: pip install cuthbert") from e
        from .linalg import psd_factor, tria

        ys, inputs, observed = check_observations(self, prior, ys, inputs, observed)
        if observed is not None:
            ys = jnp.where(observed, ys, jnp.nan)
        model_inputs = {"t": jnp.arange(ys.shape[0]), "y": ys}
        if inputs is not None:
            model_inputs["u"] = inputs

        def dynamics(step):
            mdl = self.at(step["t"])
            c = mdl.G @ mdl.process_mean + (0.0 if mdl.B is None else mdl.B @ step["u"])
            return mdl.F, c, tria(mdl.G @ psd_factor(mdl.Q))

        def observation(step):
            mdl = self.at(step["t"])
            return mdl.H, mdl.noise_mean, psd_factor(mdl.R), step["y"]

        kf = kalman.build_filter(prior.mean, psd_factor(prior.cov), dynamics, observation)
        return kf, model_inputs

    def check_horizon(self, num_steps: int) -> None:
        """Eager check that a time-varying model covers `num_steps` steps."""
        t = self.num_steps
        if t is not None and t != num_steps:
            raise ValueError(f"the model is time-varying with {t} steps but {num_steps} steps were requested")


def check_observations(
    model: Any,
    prior: Gaussian,
    ys: Any,
    inputs: Any,
    observed: Any = None,
    model_types: tuple[type, ...] = (LinearModel,),
) -> tuple[Array, Array | None, Array | None]:
    """Eager checks of a filter call; returns `ys`, `inputs` and `observed` as arrays.

    `model` must be an instance of one of `model_types`; each must provide `state_dim`,
    `obs_dim`, `check_horizon(T)` and `check_inputs(inputs, T)`. Concrete `ys` with a NaN
    in an entry to be used raise here; traced ones get `RESULTS.nan_observation`.
    """
    if not isinstance(model, model_types):
        names = " or ".join(f"jdrkf.{t.__name__}" for t in model_types)
        raise ValueError(f"model must be a {names}, got {type(model).__name__}")
    if not isinstance(prior, Gaussian):
        raise ValueError(f"prior must be a jdrkf.Gaussian, got {type(prior).__name__}")
    n, m = model.state_dim, model.obs_dim
    if prior.mean.shape != (n,):
        raise ValueError(f"prior has dimension {prior.mean.shape[-1]} but the state dimension is {n}")
    ys = as_float_array("ys", ys, (2,))
    if ys.shape[1] != m:
        raise ValueError(f"ys has shape {tuple(ys.shape)} but expected (T, {m}) (H has {m} rows)")
    model.check_horizon(ys.shape[0])
    if inputs is not None:
        inputs = as_float_array("inputs", inputs, (2,))
    model.check_inputs(inputs, ys.shape[0])
    if observed is not None:
        observed = jnp.asarray(observed)
        if observed.dtype != bool or observed.shape != ys.shape:
            raise ValueError(
                f"observed must be a boolean mask of the shape of ys, {tuple(ys.shape)} (True = use the entry), "
                f"got {observed.dtype} of shape {tuple(observed.shape)}"
            )
    if is_concrete(ys) and (observed is None or is_concrete(observed)):
        nan = np.isnan(np.asarray(ys))
        if observed is not None:
            nan &= np.asarray(observed)
        if nan.any():
            t, i = np.argwhere(nan)[0]
            hint = "" if observed is not None else "; to treat NaN entries as missing, pass observed=~jnp.isnan(ys)"
            raise ValueError(f"ys[{t}, {i}] is NaN{' but observed says to use it' if observed is not None else ''}{hint}")
    return ys, inputs, observed
