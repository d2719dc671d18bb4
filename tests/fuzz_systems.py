"""Random linear systems and the property checks of the fuzz suite (`test_fuzz.py`).

Systems: `x_k = F x_{k-1} + w`, `y_k = H x_k + v` with `n ≤ 8`, `m ≤ 4`; `F = V diag(λ) V⁻¹`
with a random well-conditioned `V` and `|λ| ≤ 0.95` (stable) or one `λ = 1` (marginally
stable); `Q`, `R` with random eigenvectors and log-uniform eigenvalues spanning a condition
number `10^c` (`c ≤ 8`). Data are simulated in NumPy (float64) and cast.

Each filter family runs with `throw=False` under `jit(vmap)` over a batch of systems of one
shape, and every run is classified:

- `reported`: a result code other than `successful` (allowed: the filter said so);
- `silent_nan`: `successful` but a non-finite output;
- `silent_non_psd`: `successful` but a filtered covariance that is not symmetric positive
  semidefinite within `psd_tolerance(dtype, n)` (relative to its trace);
- `wrong_solve`: `successful`, but the worst case of the last step disagrees with an
  independent NumPy solve (certified Frank–Wolfe, relative duality gap 1e-12) by more than
  `solve_tolerance(dtype)` (families with a per-step worst-case solver);
- `ok` otherwise.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

import jdrkf
from jdrkf.sets import KL, EpsContamination, Moment, Wasserstein
from sdp_oracles import decoupled_gradient, frank_wolfe, posterior_trace, set_lmo

NUM_STEPS = 40


def random_system(rng: np.random.Generator, n: int, m: int, cond_exp: float, marginal: bool):
    """`(F, H, Q, R)` in float64 as described in the module docstring."""
    v = rng.normal(size=(n, n)) + 2.0 * np.eye(n)
    lam = rng.uniform(-0.95, 0.95, size=n)
    if marginal:
        lam[0] = 1.0
    f = v @ np.diag(lam) @ np.linalg.inv(v)

    def cov(d):
        u, _ = np.linalg.qr(rng.normal(size=(d, d)))
        eig = 10.0 ** (-cond_exp * rng.uniform(size=d))
        eig[rng.integers(d)] = 1.0
        eig[rng.integers(d)] = 10.0**-cond_exp if d > 1 else 1.0
        return 0.5 * ((u * eig) @ u.T + ((u * eig) @ u.T).T)

    return f, rng.normal(size=(m, n)), cov(n), cov(m)


def simulate(rng: np.random.Generator, f, h, q, r, num_steps: int = NUM_STEPS):
    """One trajectory from `x_0 ~ N(0, I)`: observations `(T, m)`."""
    n, m = f.shape[0], h.shape[0]
    lq = np.linalg.cholesky(q + 1e-300 * np.eye(n)) if np.all(np.linalg.eigvalsh(q) > 0) else None
    x = rng.normal(size=n)
    ys = np.empty((num_steps, m))
    for t in range(num_steps):
        w = lq @ rng.normal(size=n) if lq is not None else rng.multivariate_normal(np.zeros(n), q)
        x = f @ x + w
        ys[t] = h @ x + np.linalg.cholesky(r) @ rng.normal(size=m)
    return ys


def families() -> dict:
    """Filter families of linear models, each with moderate robustness parameters."""
    kw = dict(throw=False, outputs="all")
    return {
        "KalmanFilter": jdrkf.KalmanFilter(**kw),
        "SteadyStateKalmanFilter": jdrkf.SteadyStateKalmanFilter(**kw),
        "DRKF-Wasserstein": jdrkf.DRKF(state_set=Wasserstein(0.1), noise_set=Wasserstein(0.1), **kw),
        "DRKF-KL": jdrkf.DRKF(state_set=KL(0.1), noise_set=KL(0.1), **kw),
        "DRKF-Moment-eps": jdrkf.DRKF(state_set=Moment(1.05), noise_set=Moment(1.05), outliers=EpsContamination(0.05, k=1.4), **kw),
        "WassersteinKF": jdrkf.WassersteinKF(0.1, **kw),
        "HuberKF": jdrkf.HuberKF(0.05, **kw),
        "RiskSensitiveKF": jdrkf.RiskSensitiveKF(1e-3, **kw),
        "TauKF": jdrkf.TauKF(0.0, 1e-3, **kw),
        "WassersteinDRKF": jdrkf.WassersteinDRKF(0.1, 0.1, **kw),
        "SteadyStateDRKF": jdrkf.SteadyStateDRKF(0.1, 0.1, **kw),
        "BCOTKF": jdrkf.BCOTKF(0.1, **kw),
        "VBKF": jdrkf.VBKF(**kw),
        "STKF": jdrkf.STKF(**kw),
        "RBKF": jdrkf.RBKF(**kw),
    }


# Per-step decoupled worst cases, re-solved independently: family -> (state set, noise set).
CHECKED_SOLVES = {
    "DRKF-Wasserstein": (("wasserstein", 0.1), ("wasserstein", 0.1)),
    "WassersteinDRKF": (("wasserstein", 0.1), ("wasserstein", 0.1)),
    "DRKF-KL": (("kl", 0.1), ("kl", 0.1)),
}


def psd_tolerance(dtype, n: int) -> float:
    """Relative tolerance of the symmetry/PSD checks: `100 n eps(dtype)`."""
    return 100.0 * n * float(np.finfo(dtype).eps)


def solve_tolerance(dtype) -> float:
    """Relative agreement of a converged worst case with the independent solve."""
    return 1e-6 if dtype == np.float64 else 2e-3


def independent_posterior_trace(spec_x, spec_v, nominal_prior, h, r) -> float:
    """Trace of the worst-case posterior covariance by the certified NumPy Frank–Wolfe."""
    (sx, sv), _, _ = frank_wolfe(
        lambda a, b: posterior_trace(a, h, b),
        lambda a, b: decoupled_gradient(a, h, b),
        [lambda g: set_lmo(spec_x, g, nominal_prior), lambda g: set_lmo(spec_v, g, r)],
        [nominal_prior, r],
        rtol=1e-12,
    )
    return float(posterior_trace(sx, h, sv))


@dataclasses.dataclass
class Counts:
    ok: int = 0
    reported: int = 0
    silent_nan: int = 0
    silent_non_psd: int = 0
    wrong_solve: int = 0

    def add(self, other: "Counts") -> None:
        for f in dataclasses.fields(self):
            setattr(self, f.name, getattr(self, f.name) + getattr(other, f.name))

    @property
    def violations(self) -> int:
        return self.silent_nan + self.silent_non_psd + self.wrong_solve


_RUNNERS: dict = {}


def _runner(name: str, flt):
    """`jit(vmap)` over systems (model and observations), compiled once per family, shape and dtype."""
    if name not in _RUNNERS:
        _RUNNERS[name] = jax.jit(jax.vmap(lambda model, prior, ys: flt(model, prior, ys), in_axes=(0, None, 0)))
    return _RUNNERS[name]


def check_batch(name: str, flt, systems, ys, dtype, max_solve_checks: int = 3) -> tuple[Counts, list[str]]:
    """Run `flt` on a batch of systems of one shape; classify every run (see module docstring)."""
    f, h, q, r = (np.stack(a) for a in zip(*systems, strict=True))
    n = f.shape[-1]
    cast = lambda a: jnp.asarray(a, dtype)  # noqa: E731
    models = [jdrkf.LinearModel(F=cast(a), H=cast(c), Q=cast(w), R=cast(v)) for a, c, w, v in systems]
    model = jax.tree.map(lambda *xs: jnp.stack(xs), *models)
    prior = jdrkf.Gaussian(jnp.zeros(n, dtype), jnp.eye(n, dtype=dtype))
    res = _runner(name, flt)(model, prior, cast(np.stack(ys)))
    codes = np.asarray(res.result._value)
    ok_code = int(jdrkf.RESULTS.successful._value)
    leaves = [np.asarray(x) for x in jax.tree.leaves((res.filtered_means, res.filtered_covariances, res.predicted_means,
                                                      res.predicted_covariances, res.marginal_loglik))]
    covs = np.asarray(res.filtered_covariances, np.float64)
    tol = psd_tolerance(dtype, n)
    counts, notes = Counts(), []
    checked = 0
    for b in range(codes.shape[0]):
        if codes[b] != ok_code:
            counts.reported += 1
            continue
        if not all(np.all(np.isfinite(x[b])) for x in leaves):
            counts.silent_nan += 1
            notes.append(f"{name} system {b}: non-finite output marked successful")
            continue
        p = covs[b]
        scale = np.maximum(np.abs(np.trace(p, axis1=-2, axis2=-1)), np.finfo(dtype).tiny)
        asym = np.abs(p - np.swapaxes(p, -1, -2)).max(axis=(-1, -2)) / scale
        lmin = np.linalg.eigvalsh(0.5 * (p + np.swapaxes(p, -1, -2)))[:, 0] / scale
        if np.any(asym > tol) or np.any(lmin < -tol):
            counts.silent_non_psd += 1
            notes.append(f"{name} system {b}: filtered covariance asymmetry {asym.max():.2g}, min eig {lmin.min():.2g} (relative to the trace)")
            continue
        if name in CHECKED_SOLVES and checked < max_solve_checks:
            checked += 1
            nominal = np.asarray(res.info["nominal_prior_cov"][b, -1], np.float64)
            ref = independent_posterior_trace(*CHECKED_SOLVES[name], nominal, h[b], r[b])
            got = float(np.trace(covs[b, -1]))
            if abs(got - ref) > solve_tolerance(dtype) * abs(ref):
                counts.wrong_solve += 1
                notes.append(f"{name} system {b}: last-step posterior trace {got:.10g}, independent solve {ref:.10g}")
                continue
        counts.ok += 1
    return counts, notes


def run_fuzz(cases, families_: dict | None = None, batch: int = 4, max_solve_checks: int = 3):
    """`cases`: iterable of `(seed, n, m, cond_exp, marginal, dtype)`; each case is a batch of
    `batch` systems of that shape. Returns per-family `Counts` and the notes of violations."""
    families_ = families() if families_ is None else families_
    totals = {name: Counts() for name in families_}
    notes: list[str] = []
    # Grouped by shape and dtype: each group compiles every family once; the compiled code is
    # dropped between groups (hundreds of executables would exhaust the process's mappings).
    key = None
    for seed, n, m, cond_exp, marginal, dtype in sorted(cases, key=lambda c: (c[1], c[2], np.dtype(c[5]).name)):
        if key != (n, m, np.dtype(dtype).name):
            key = (n, m, np.dtype(dtype).name)
            _RUNNERS.clear()
            jax.clear_caches()
        rng = np.random.default_rng(seed)
        systems = [random_system(rng, n, m, cond_exp, marginal) for _ in range(batch)]
        ys = [simulate(rng, *s) for s in systems]
        for name, flt in families_.items():
            c, nt = check_batch(name, flt, systems, ys, dtype, max_solve_checks)
            totals[name].add(c)
            notes += [f"[seed {seed}, n={n}, m={m}, cond=1e{cond_exp:g}, {np.dtype(dtype).name}] {x}" for x in nt]
    return totals, notes
