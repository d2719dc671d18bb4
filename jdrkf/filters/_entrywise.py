"""The Kalman step on matrix entries, for small states (`n, m ≤ linalg.UNROLL_MAX`).

A vector is a tuple of scalar arrays and a matrix a tuple of rows. Under `jax.vmap` over
runs every entry becomes one contiguous `(B,)` array, so all the arithmetic of a step has
one shape and XLA fuses it into a few loops over the runs. The same step on `(B, n, n)`
arrays mixes shapes (`(B, n, n)`, `(B, m, n)`, `(B, n)`, `(B,)`), which XLA cannot fuse
together, and costs 3–4× more per run and step when every run has its own covariances
(missing data, `benchmarks/kf_throughput.py`). The arithmetic is that of `predict` and
`update` in `_kalman.py` (Joseph form, missing rows decoupled as in `masked_measurement`)
and of `step_result`; tests check the two against each other and against NumPy.

Package-internal: `KalmanFilter` uses it; it is not part of the public API.
"""

from __future__ import annotations

import math

import jax.numpy as jnp
from jaxtyping import Array

from .. import linalg
from .._gaussian import Gaussian
from .._validation import psd_rtol
from ._base import RESULTS, StepOutput

Vec = tuple[Array, ...]
Mat = tuple[Vec, ...]


def applies(n: int, m: int) -> bool:
    """Whether states of size `n` with `m` observations use the entrywise step."""
    return linalg.unrolls(n) and linalg.unrolls(m)


def vec(x) -> Vec:
    return tuple(x[i] for i in range(x.shape[0]))


def mat(a) -> Mat:
    return tuple(tuple(a[i, j] for j in range(a.shape[1])) for i in range(a.shape[0]))


def gaussian(belief: Gaussian) -> tuple[Vec, Mat]:
    """The state `kalman_step` carries: the entries of the mean and covariance."""
    return vec(belief.mean), mat(belief.cov)


def stack_vec(x: Vec) -> Array:
    return jnp.stack(x)


def stack_mat(a: Mat) -> Array:
    return jnp.stack([jnp.stack(row) for row in a])


def _sum(terms):
    terms = list(terms)
    return sum(terms[1:], start=terms[0])


def matvec(a: Mat, x: Vec) -> Vec:
    return tuple(_sum(aij * xj for aij, xj in zip(row, x)) for row in a)


def matmul(a: Mat, b: Mat) -> Mat:
    cols = tuple(zip(*b))
    return tuple(tuple(_sum(aik * bkj for aik, bkj in zip(row, col)) for col in cols) for row in a)


def transpose(a: Mat) -> Mat:
    return tuple(zip(*a))


def add(a: Mat, b: Mat) -> Mat:
    return tuple(tuple(x + y for x, y in zip(ra, rb)) for ra, rb in zip(a, b))


def symmetrize(a: Mat) -> Mat:
    """`(a + aᵀ) / 2`, each off-diagonal entry computed once and shared by both positions."""
    n = len(a)
    low = {(i, j): 0.5 * (a[i][j] + a[j][i]) for i in range(n) for j in range(i)}
    return tuple(tuple(a[i][i] if i == j else low[max(i, j), min(i, j)] for j in range(n)) for i in range(n))


def cholesky(a: Mat) -> Mat:
    """Lower factor as `linalg.cholesky` (NaN from a non-positive pivot on)."""
    n = len(a)
    low = [[None] * n for _ in range(n)]
    for j in range(n):
        s = a[j][j] - sum(low[j][k] ** 2 for k in range(j))
        low[j][j] = jnp.where(s > 0, jnp.sqrt(jnp.where(s > 0, s, 1.0)), jnp.nan)
        for i in range(j + 1, n):
            low[i][j] = (a[i][j] - sum(low[i][k] * low[j][k] for k in range(j))) / low[j][j]
    zero = jnp.zeros_like(a[0][0])
    return tuple(tuple(low[i][j] if j <= i else zero for j in range(n)) for i in range(n))


def forward(low: Mat, b: Vec) -> Vec:
    """`L⁻¹ b` for a lower factor `L`."""
    z = []
    for i, row in enumerate(low):
        z.append((b[i] - sum(row[k] * z[k] for k in range(i))) / row[i])
    return tuple(z)


def backward(low: Mat, z: Vec) -> Vec:
    """`L⁻ᵀ z` for a lower factor `L`."""
    n = len(low)
    x = [None] * n
    for i in reversed(range(n)):
        x[i] = (z[i] - sum(low[k][i] * x[k] for k in range(i + 1, n))) / low[i][i]
    return tuple(x)


def is_psd(cov: Mat) -> Array:
    """`_steps.is_psd` on entries: every pivot of `cov + (c n eps Tr cov + tiny) I` is
    positive (non-finite entries are reported by the caller's finiteness check)."""
    n = len(cov)
    dtype = cov[0][0].dtype
    shift = psd_rtol(dtype, n) * jnp.abs(_sum(cov[i][i] for i in range(n))) + jnp.finfo(dtype).tiny
    shifted = tuple(tuple(c + shift if i == j else c for j, c in enumerate(row)) for i, row in enumerate(cov))
    low = cholesky(shifted)
    return _all(jnp.isfinite(low[i][i]) for i in range(n))


def _all(flags) -> Array:
    flags = list(flags)
    out = flags[0]
    for f in flags[1:]:
        out = out & f
    return out


def _finite(a: Mat) -> Array:
    return _all(jnp.isfinite(x) for row in a for x in row)


def kalman_step(model, state: tuple[Vec, Mat], y, t, u=None, observed=None) -> tuple[tuple[Vec, Mat], StepOutput]:
    """One `KalmanFilter` step (`predict`, then `update` with `observed`, then
    `step_result`) on entries; `state` is `(vec(mean), mat(cov))`."""
    mdl = model.at(t)
    mean, cov = state
    f, g = mat(mdl.F), mat(mdl.G)
    # predict: m⁻ = F m + B u + G μ_w, P⁻ = F P Fᵀ + G Q Gᵀ
    mean_pred = tuple(a + b for a, b in zip(matvec(f, mean), matvec(g, vec(mdl.process_mean))))
    if mdl.B is not None:
        mean_pred = tuple(a + b for a, b in zip(mean_pred, matvec(mat(mdl.B), vec(u))))
    gqg = matmul(matmul(g, mat(mdl.Q)), transpose(g))
    cov_pred = symmetrize(add(matmul(matmul(f, cov), transpose(f)), gqg))
    # update (Joseph form); missing rows decoupled: zero H row and residual, unit variance
    h, r = mat(mdl.H), mat(mdl.R)
    m = len(h)
    resid = tuple(yi - mu for yi, mu in zip(vec(y), vec(mdl.noise_mean)))
    if observed is None:
        num_observed = m
    else:
        obs = vec(observed.astype(y.dtype))
        h = tuple(tuple(hij * obs[i] for hij in row) for i, row in enumerate(h))
        r = tuple(tuple(r[i][j] * obs[i] * obs[j] + (1.0 - obs[i] if i == j else 0.0) for j in range(m)) for i in range(m))
        resid = tuple(jnp.where(observed[i], resid[i], 0.0) for i in range(m))
        num_observed = _sum(obs)
    innov = tuple(ri - hm for ri, hm in zip(resid, matvec(h, mean_pred)))
    hp = matmul(h, cov_pred)
    chol_s = cholesky(symmetrize(add(matmul(hp, transpose(h)), r)))
    failed = ~_finite(chol_s)
    gain = tuple(backward(chol_s, forward(chol_s, col)) for col in zip(*hp))  # row j of K = (S⁻¹ H P)ᵀ: S⁻¹ (HP)[:, j]
    mean_filt = tuple(a + b for a, b in zip(mean_pred, matvec(gain, innov)))
    n = len(mean)
    kh = matmul(gain, h)
    a = tuple(tuple((1.0 - kh[i][j]) if i == j else -kh[i][j] for j in range(n)) for i in range(n))
    cov_filt = symmetrize(add(matmul(matmul(a, cov_pred), transpose(a)), matmul(matmul(gain, r), transpose(gain))))
    # log N(innov; 0, S) over the observed components (`log_density`)
    z = forward(chol_s, innov)
    quad = _sum(zi * zi for zi in z)
    logdet = 2.0 * _sum(jnp.log(chol_s[i][i]) for i in range(m))
    loglik = -0.5 * (quad + logdet + num_observed * math.log(2 * math.pi))
    # result code (`step_result`)
    code = RESULTS.where(is_psd(cov_filt), RESULTS.successful, RESULTS.indefinite_covariance)
    code = RESULTS.where(_finite(cov_filt), code, RESULTS.nonfinite_state)
    result = RESULTS.where(failed, RESULTS.nonpositive_innovation, code)
    pred = Gaussian(stack_vec(mean_pred), stack_mat(cov_pred))
    filt = Gaussian(stack_vec(mean_filt), stack_mat(cov_filt))
    out = StepOutput(predicted=pred, filtered=filt, loglik=loglik, info=None, result=result)
    return (mean_filt, cov_filt), out
