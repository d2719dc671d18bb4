"""Linear state-space models with optional time variation and control inputs."""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float, Int

from ._validation import as_float_array, check_covariance, check_shape, check_time_axis


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

    def check_horizon(self, num_steps: int) -> None:
        """Eager check that a time-varying model covers `num_steps` steps."""
        t = self.num_steps
        if t is not None and t != num_steps:
            raise ValueError(f"the model is time-varying with {t} steps but {num_steps} steps were requested")
