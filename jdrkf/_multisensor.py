"""Multi-sensor linear models with (possibly) correlated sensor noises (Chen et al. 2025)."""

from __future__ import annotations

from typing import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jaxtyping import Array, ArrayLike, Float, PRNGKeyArray

from . import linalg
from ._gaussian import Gaussian
from ._models import LinearModel
from ._noise import AbstractNoise
from ._simulate import AbstractSelfSimulatingModel, Trajectories, check_law
from ._validation import as_float_array, check_covariance, check_shape, is_concrete


def _offsets(dims: tuple[int, ...]) -> tuple[int, ...]:
    return tuple(int(x) for x in np.concatenate([[0], np.cumsum(dims)]))


def _block_diag(blocks) -> Array:
    m = sum(b.shape[0] for b in blocks)
    out = jnp.zeros((m, m), blocks[0].dtype)
    o = 0
    for b in blocks:
        d = b.shape[0]
        out = out.at[o:o + d, o:o + d].set(b)
        o += d
    return out


class MultiSensorModel(AbstractSelfSimulatingModel):
    r"""Linear model observed by `p` sensors (Chen et al. 2025, eqs. 27–28 and 34).

    For `k = 1..T`: `x_k = F x_{k-1} + G w_k`, `w_k ~ N(0, Q)`, and for sensor `i`:
    `y_k^i = H_i x_k + v_k^i`. The **nominal** model (what filters assume) has
    independent sensor noises `v_k^i ~ N(0, R_i)`, plus the known cross-covariances
    `cross_cov` if given. The **true** data (`simulate`) use eq. 34:
    `v_k^i = β_i w_{k-1} + η_k^i`, `η_k ~ N(0, R_full)`, so the sensor noises are
    correlated with each other and with the previous process noise.

    **Arguments:**

    - `F`: `(n, n)`; `G`: `(n, q)` (default identity); `Q`: `(q, q)`.
    - `H`: sequence of `p` blocks `(m_i, n)`; `R`: sequence of `p` blocks `(m_i, m_i)`.
    - `cross_cov`: known cross-covariances of the sensor noises, a dict `{(i, j): (m_i, m_j)}`
      (`i ≠ j`; the transpose is implied) or a full `(m, m)` matrix whose diagonal blocks
      equal the `R_i` (or are zero); `None` = unknown, zero in the nominal model.
    - `beta`: per-sensor `(m_i, q)` matrices (scalars allowed when `m_i = q = 1`) or a
      stacked `(m, q)` array for the true data; `None` = no correlation.

    Time-invariant only (no time axis, no controls, zero noise means).
    """

    F: Float[Array, "n n"]
    G: Float[Array, "n q"]
    Q: Float[Array, "q q"]
    H: Float[Array, "m n"]
    R: Float[Array, "m m"]
    cross_cov: Float[Array, "m m"] | None
    beta: Float[Array, "m q"] | None
    dims: tuple[int, ...] = eqx.field(static=True)

    def __init__(
        self,
        F: Float[ArrayLike, "n n"],
        H: Sequence[Float[ArrayLike, "mi n"]],
        Q: Float[ArrayLike, "q q"],
        R: Sequence[Float[ArrayLike, "mi mi"]],
        G: Float[ArrayLike, "n q"] | None = None,
        cross_cov: dict | Float[ArrayLike, "m m"] | None = None,
        beta: Sequence | Float[ArrayLike, "m q"] | None = None,
    ):
        F = as_float_array("F", F, (2,))
        Q = as_float_array("Q", Q, (2,))
        n = F.shape[0]
        check_shape("F", F, (n, n), "(F must be square)")
        check_covariance("Q", Q)
        q = Q.shape[0]
        if G is None:
            if q != n:
                raise ValueError(f"Q has shape {tuple(Q.shape)} but the state dimension is {n}; pass G of shape ({n}, {q})")
            G = jnp.eye(n, dtype=F.dtype)
        G = as_float_array("G", G, (2,))
        check_shape("G", G, (n, q), f"since the state dimension is {n} and Q is {q}x{q}")
        if isinstance(H, (jax.Array, np.ndarray)) or isinstance(R, (jax.Array, np.ndarray)):
            raise ValueError("H and R must be sequences (lists/tuples) of per-sensor blocks, e.g. H=[H1, H2], R=[R1, R2]")
        H, R = list(H), list(R)
        if len(H) == 0 or len(H) != len(R):
            raise ValueError(f"H and R must be non-empty sequences of equal length (one block per sensor), got {len(H)} and {len(R)}")
        hs, rs = [], []
        for i, (h, r) in enumerate(zip(H, R, strict=True)):
            h = as_float_array(f"H[{i}]", h, (2,))
            check_shape(f"H[{i}]", h, (None, n), f"since the state dimension is {n}")
            r = as_float_array(f"R[{i}]", r, (2,))
            check_covariance(f"R[{i}]", r)
            check_shape(f"R[{i}]", r, (h.shape[0], h.shape[0]), f"since H[{i}] has {h.shape[0]} rows")
            hs.append(h)
            rs.append(r)
        dims = tuple(int(h.shape[0]) for h in hs)
        offs = _offsets(dims)
        m = offs[-1]
        dtype = jnp.result_type(F, Q, G, *hs, *rs)

        cc = None
        if cross_cov is not None:
            cc = jnp.zeros((m, m), dtype)
            if isinstance(cross_cov, dict):
                for key, block in cross_cov.items():
                    if not (isinstance(key, tuple) and len(key) == 2 and all(isinstance(k, int) for k in key)):
                        raise ValueError(f"cross_cov keys must be pairs of sensor indices (i, j), got {key!r}")
                    i, j = key
                    if not (0 <= i < len(dims) and 0 <= j < len(dims)) or i == j:
                        raise ValueError(f"cross_cov key {key} must be two different sensor indices in 0..{len(dims) - 1}")
                    block = as_float_array(f"cross_cov[{key}]", block, (2,)).astype(dtype)
                    check_shape(f"cross_cov[{key}]", block, (dims[i], dims[j]), f"(sensor {i} has {dims[i]} and sensor {j} has {dims[j]} outputs)")
                    cc = cc.at[offs[i]:offs[i + 1], offs[j]:offs[j + 1]].set(block)
                    cc = cc.at[offs[j]:offs[j + 1], offs[i]:offs[i + 1]].set(block.T)
            else:
                full = as_float_array("cross_cov", cross_cov, (2,)).astype(dtype)
                check_shape("cross_cov", full, (m, m), f"(the stacked measurement has dimension {m})")
                check_covariance("cross_cov", full)
                for i in range(len(dims)):
                    sl = slice(offs[i], offs[i + 1])
                    if is_concrete(full):
                        blk = np.asarray(full[sl, sl])
                        if not (np.allclose(blk, 0.0) or np.allclose(blk, np.asarray(rs[i]), rtol=1e-8, atol=1e-12)):
                            raise ValueError(f"the diagonal block {i} of cross_cov must be zero or equal R[{i}]")
                    full = full.at[sl, sl].set(0.0)
                cc = full
            if is_concrete(cc) and all(is_concrete(r) for r in rs):
                r_full = np.asarray(_block_diag([r.astype(dtype) for r in rs]) + cc, dtype=np.float64)
                if np.min(np.linalg.eigvalsh(r_full)) < -1e-10 * max(1.0, np.max(np.abs(r_full))):
                    raise ValueError("R together with cross_cov is not positive semidefinite")

        b = None
        if beta is not None:
            if isinstance(beta, (list, tuple)):
                if len(beta) != len(dims):
                    raise ValueError(f"beta must have one entry per sensor ({len(dims)}), got {len(beta)}")
                blocks = []
                for i, bi in enumerate(beta):
                    bi = as_float_array(f"beta[{i}]", bi, (0, 1, 2))
                    if bi.ndim < 2:
                        if dims[i] * q != bi.size or bi.size != 1:
                            raise ValueError(f"beta[{i}] is a scalar but sensor {i} has {dims[i]} outputs and q = {q}; pass a ({dims[i]}, {q}) matrix")
                        bi = bi.reshape(1, 1)
                    check_shape(f"beta[{i}]", bi, (dims[i], q), f"(sensor {i} has {dims[i]} outputs and Q is {q}x{q})")
                    blocks.append(bi)
                b = jnp.concatenate([x.astype(dtype) for x in blocks], axis=0)
            else:
                b = as_float_array("beta", beta, (2,))
                check_shape("beta", b, (m, q), f"(stacked measurement dimension {m}, Q is {q}x{q})")
        self.F, self.G, self.Q = F.astype(dtype), G.astype(dtype), Q.astype(dtype)
        self.H = jnp.concatenate([h.astype(dtype) for h in hs], axis=0)
        self.R = _block_diag([r.astype(dtype) for r in rs])
        self.cross_cov = cc
        self.beta = None if b is None else b.astype(dtype)
        self.dims = dims

    # -- interface shared with LinearModel ------------------------------------------
    @property
    def num_sensors(self) -> int:
        return len(self.dims)

    @property
    def state_dim(self) -> int:
        return self.F.shape[-1]

    @property
    def obs_dim(self) -> int:
        return sum(self.dims)

    @property
    def num_steps(self) -> None:
        return None

    def at(self, t) -> "MultiSensorModel":
        return self

    def check_horizon(self, num_steps: int) -> None:
        """Time-invariant: any horizon is fine."""

    def check_inputs(self, inputs, num_steps: int) -> None:
        if inputs is not None:
            raise ValueError("inputs were given but MultiSensorModel has no control matrix")

    def _simulate_runs(self, key, prior, num_steps, num_runs):
        return _simulate_multisensor(key, self, prior, num_steps, num_runs)

    # -- views ---------------------------------------------------------------------
    def _slice(self, i: int) -> slice:
        if not 0 <= i < self.num_sensors:
            raise ValueError(f"sensor index must be in 0..{self.num_sensors - 1}, got {i}")
        offs = _offsets(self.dims)
        return slice(offs[i], offs[i + 1])

    def noise_cov(self) -> Float[Array, "m m"]:
        """Nominal stacked measurement-noise covariance: block-diagonal `R` plus the known `cross_cov`."""
        return self.R if self.cross_cov is None else self.R + self.cross_cov

    def as_linear(self) -> LinearModel:
        """The centralized nominal model (stacked `H`, noise covariance `noise_cov()`)."""
        return LinearModel(F=self.F, H=self.H, Q=self.Q, R=self.noise_cov(), G=self.G)

    def sensor(self, i: int) -> LinearModel:
        """The single-sensor model of sensor `i` (its rows of `H` and block `R_i`)."""
        sl = self._slice(i)
        return LinearModel(F=self.F, H=self.H[sl], Q=self.Q, R=self.R[sl, sl], G=self.G)

    def joint_nominal_cov(self, P: Float[ArrayLike, "n n"], *, zero_cross: bool = False) -> Float[Array, "n+m n+m"]:
        """Nominal covariance of `(x_k, y_k^1..y_k^p)` given the previous posterior covariance `P`
        (eqs. 30–31): with `M = F P Fᵀ + G Q Gᵀ`, `[[M, M Hᵀ], [H M, H M Hᵀ + R]]` where `R` is the
        block-diagonal nominal noise covariance (sensor noises independent; known `cross_cov` is
        not used: the marginal problem treats cross-sensor blocks as free).

        The marginal blocks `(x, y^i)` are those of the authors' `reconstruct`; their full matrix
        sets the cross-sensor blocks `Σ_{y^i y^j}` to zero (`zero_cross=True` reproduces it; that
        matrix is in general not PSD). The default keeps `H_i M H_jᵀ`, a valid (PSD) covariance.
        """
        P = jnp.asarray(P, self.F.dtype)
        m_pred = linalg.symmetrize(self.F @ P @ self.F.T + self.G @ self.Q @ self.G.T)
        cross = m_pred @ self.H.T
        syy = linalg.symmetrize(self.H @ cross + self.R)
        if zero_cross:
            mask = _block_diag([jnp.ones((d, d), syy.dtype) for d in self.dims])
            syy = syy * mask
        return jnp.block([[m_pred, cross], [cross.T, syy]])

    def true_noise_cov(self) -> Float[Array, "m m"]:
        """Exact covariance of the stacked true noise `v_k = β w_{k-1} + η_k` (eq. 34):
        `β Q βᵀ + R + cross_cov` (the authors' commented `b_i b_j q1 + diag(q1i)`)."""
        base = self.noise_cov()
        return base if self.beta is None else linalg.symmetrize(self.beta @ self.Q @ self.beta.T + base)

    def true_noise_process_cross_cov(self) -> Float[Array, "m q"]:
        """`Cov(v_k, w_{k-1}) = β Q` of the true data (zero without `beta`)."""
        if self.beta is None:
            return jnp.zeros((self.obs_dim, self.Q.shape[0]), self.F.dtype)
        return self.beta @ self.Q


def _simulate_multisensor(
    key: PRNGKeyArray,
    model: MultiSensorModel,
    prior: Gaussian | AbstractNoise,
    num_steps: int,
    num_runs: int,
) -> Trajectories:
    """Simulate the *true* data of eq. 34: `x_k = F x_{k-1} + G w_k`, `y_k = H x_k + β w_{k-1} + η_k`,
    `w ~ N(0, Q)`, `η_k ~ N(0, R + cross_cov)`; `w_0` is an extra draw independent of `x_0` (so the
    noise law is stationary from `k = 1`). Run `r` uses `jax.random.fold_in(key, r)`.
    `clean_observations` equal `observations` (no outliers)."""
    if key is None:
        raise ValueError("simulate needs a PRNG key, e.g. jax.random.key(0)")
    if not isinstance(model, MultiSensorModel):
        raise ValueError(f"model must be a jdrkf.MultiSensorModel, got {type(model).__name__}")
    num_steps, num_runs = int(num_steps), int(num_runs)
    if num_steps < 1 or num_runs < 1:
        raise ValueError(f"num_steps and num_runs must be positive, got {num_steps} and {num_runs}")
    prior = check_law("prior", prior, model.state_dim, model.F.dtype)
    return _simulate_ms(key, model, prior, num_steps, num_runs)


@eqx.filter_jit
def _simulate_ms(key, model, prior, num_steps, num_runs):
    m, q = model.obs_dim, model.Q.shape[0]
    dtype = model.F.dtype
    # Square roots once, outside the vmap over runs (no batched LAPACK).
    root_q = linalg.psd_sqrt(model.Q)
    root_r = linalg.psd_sqrt(model.noise_cov())
    beta = jnp.zeros((m, q), dtype) if model.beta is None else model.beta

    def one_run(run_key):
        k0, kw0, kseq = jax.random.split(run_key, 3)
        x0 = prior.sample(k0, 0)
        w0 = root_q @ jax.random.normal(kw0, (q,), dtype)

        def body(carry, kt):
            x, w_prev = carry
            kw, kv = jax.random.split(kt)
            w = root_q @ jax.random.normal(kw, (q,), dtype)
            x_new = model.F @ x + model.G @ w
            v = beta @ w_prev + root_r @ jax.random.normal(kv, (m,), dtype)
            return (x_new, w), (x_new, model.H @ x_new + v)

        _, (states, ys) = lax.scan(body, (x0, w0), jax.random.split(kseq, num_steps))
        return x0, states, ys

    run_keys = jax.vmap(lambda r: jax.random.fold_in(key, r))(jnp.arange(num_runs))
    x0, states, ys = jax.vmap(one_run)(run_keys)
    return Trajectories(
        initial_states=x0,
        states=states,
        observations=ys,
        clean_observations=ys,
        outliers=jnp.zeros(ys.shape, bool),
        transition_matrices=None,
    )
