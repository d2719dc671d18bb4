"""The naming rule for radii (README, Conventions → Names): the size of a ball is `radius`
(`radius_x`, `radius_v` for a ball on the state and one on the noise); the former names
are deprecated aliases (keyword and read-only attribute) for one release."""

from __future__ import annotations

import ast
import dataclasses
import pathlib

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jdrkf
from jdrkf.sets import KL, MarginalKL, Wasserstein

# (constructor, positional arguments before the renamed ones, {new: (old, value)})
CASES = {
    "Wasserstein": (Wasserstein, (), {"radius": ("theta", 0.3)}),
    "KL": (KL, (), {"radius": ("c", 0.2)}),
    "MarginalKL": (MarginalKL, (), {"radius": ("c", np.array([0.1, 0.2]))}),
    "WassersteinKF": (jdrkf.WassersteinKF, (), {"radius": ("rho", 0.1)}),
    "TauKF": (jdrkf.TauKF, (0.5,), {"radius": ("c", 1e-3)}),
    "WassersteinDRKF": (jdrkf.WassersteinDRKF, (), {"radius_x": ("theta_x", 0.4), "radius_v": ("theta_v", 0.2)}),
    "SteadyStateDRKF": (jdrkf.SteadyStateDRKF, (), {"radius_x": ("theta_x", 0.4), "radius_v": ("theta_v", 0.2)}),
}
IDS = list(CASES)


def _same(a, b):
    la, ta = jax.tree_util.tree_flatten(a)
    lb, tb = jax.tree_util.tree_flatten(b)
    assert ta == tb
    for x, y in zip(la, lb, strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


@pytest.mark.parametrize("name", IDS)
def test_new_keyword_and_positional(name):
    cls, pos, renames = CASES[name]
    new = cls(*pos, **{k: v for k, (_, v) in renames.items()})
    positional = cls(*pos, *(v for _, v in renames.values()))
    _same(new, positional)
    for k, (_, v) in renames.items():
        np.testing.assert_array_equal(np.asarray(getattr(new, k)), np.asarray(v, dtype=np.asarray(getattr(new, k)).dtype))


@pytest.mark.parametrize("name", IDS)
def test_old_keyword_warns_and_gives_the_same_object(name):
    cls, pos, renames = CASES[name]
    new = cls(*pos, **{k: v for k, (_, v) in renames.items()})
    for k, (old, v) in renames.items():
        others = {kk: vv for kk, (_, vv) in renames.items() if kk != k}
        with pytest.warns(DeprecationWarning, match=rf"{old}=.*deprecated.*\b{k}="):
            legacy = cls(*pos, **others, **{old: v})
        _same(new, legacy)


@pytest.mark.parametrize("name", IDS)
def test_old_attribute_warns_and_returns_the_new_value(name):
    cls, pos, renames = CASES[name]
    obj = cls(*pos, **{k: v for k, (_, v) in renames.items()})
    for k, (old, _) in renames.items():
        with pytest.warns(DeprecationWarning, match=rf"\.{old} is deprecated; use \.{k}\b"):
            value = getattr(obj, old)
        assert value is getattr(obj, k)
        with pytest.raises(AttributeError):
            setattr(obj, old, 1.0)


@pytest.mark.parametrize("name", IDS)
def test_both_keywords_is_an_error(name):
    cls, pos, renames = CASES[name]
    k, (old, v) = next(iter(renames.items()))
    others = {kk: vv for kk, (_, vv) in renames.items() if kk != k}
    with pytest.raises(TypeError, match=rf"both '{k}' and .* '{old}'"):
        cls(*pos, **others, **{k: v, old: v})


@pytest.mark.parametrize("name", IDS)
def test_alias_is_not_a_leaf_and_tree_at_uses_the_new_name(name):
    cls, pos, renames = CASES[name]
    obj = cls(*pos, **{k: v for k, (_, v) in renames.items()})
    k = next(iter(renames))
    fields = {f.name for f in dataclasses.fields(obj)}
    assert k in fields and not fields & {old for old, _ in renames.values()}
    leaves = jax.tree_util.tree_leaves(obj)
    assert sum(leaf is getattr(obj, k) for leaf in leaves) == 1  # the field is a leaf once; the alias is none
    moved = eqx.tree_at(lambda s: getattr(s, k), obj, jnp.asarray(getattr(obj, k)) + 1.0)
    np.testing.assert_allclose(np.asarray(getattr(moved, k)), np.asarray(getattr(obj, k)) + 1.0)


def test_wasserstein_mmse_aliases():
    from jdrkf.sets import wasserstein_mmse, wasserstein_mmse_joint

    M, H, R = np.eye(2), np.array([[1.0, 0.0]]), np.eye(1)
    new = wasserstein_mmse(M, H, R, radius_x=0.2, radius_v=0.1)
    with pytest.warns(DeprecationWarning, match="radius_x="):
        old = wasserstein_mmse(M, H, R, theta_x=0.2, radius_v=0.1)
    np.testing.assert_array_equal(new.state_cov, old.state_cov)
    with pytest.raises(TypeError, match="both"):
        wasserstein_mmse(M, H, R, 0.2, 0.1, theta_x=0.2)
    S = np.eye(3)
    new = wasserstein_mmse_joint(S, 2, radius=0.1)
    with pytest.warns(DeprecationWarning, match="radius="):
        old = wasserstein_mmse_joint(S, 2, rho=0.1)
    np.testing.assert_array_equal(new.cov, old.cov)


def test_missing_radius_is_a_type_error():
    with pytest.raises(TypeError, match="missing required argument 'radius'"):
        Wasserstein()
    with pytest.raises(TypeError, match="missing required argument 'radius_v'"):
        jdrkf.WassersteinDRKF(0.1)


# ------------------------------------------------------------------ no old names in jdrkf

_ROOT = pathlib.Path(jdrkf.__file__).parent
_OLD_KEYWORDS = {
    "Wasserstein": {"theta"},
    "KL": {"c"},
    "MarginalKL": {"c"},
    "WassersteinKF": {"rho"},
    "TauKF": {"c"},
    "WassersteinDRKF": {"theta_x", "theta_v"},
    "SteadyStateDRKF": {"theta_x", "theta_v"},
    "steady_state_worst_case": {"theta_x", "theta_v"},
    "wasserstein_mmse": {"theta_x", "theta_v"},
    "wasserstein_mmse_joint": {"rho"},
}
# Attributes that only the renamed classes had (`.theta` is also RiskSensitiveKF's and `.c`
# is used elsewhere, so those are checked on the sets' and filters' typical receivers).
_OLD_ATTRIBUTES = {"theta_x", "theta_v", "rho"}
_SET_RECEIVERS = {"set", "state_set", "noise_set", "joint_set", "prior_set"}


def _callee(node: ast.Call) -> str | None:
    f = node.func
    return f.id if isinstance(f, ast.Name) else f.attr if isinstance(f, ast.Attribute) else None


def _offences(path: pathlib.Path) -> list[str]:
    tree = ast.parse(path.read_text(), str(path))
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Call) and (name := _callee(node)) in _OLD_KEYWORDS:
            out += [f"{path}:{node.lineno}: {name}({kw.arg}=...)" for kw in node.keywords if kw.arg in _OLD_KEYWORDS[name]]
        if isinstance(node, ast.Attribute) and isinstance(node.ctx, ast.Load):
            if node.attr in {"theta_x", "theta_v"} and isinstance(node.value, ast.Name) and node.value.id == "self":
                out.append(f"{path}:{node.lineno}: self.{node.attr}")
            receiver = node.value.attr if isinstance(node.value, ast.Attribute) else getattr(node.value, "id", None)
            if node.attr in {"theta", "c"} | _OLD_ATTRIBUTES and receiver in _SET_RECEIVERS:
                out.append(f"{path}:{node.lineno}: {receiver}.{node.attr}")
    return out


def test_no_module_uses_the_old_names():
    skip = {_ROOT / "_validation.py"}  # the alias helper
    bad = [o for p in sorted(_ROOT.rglob("*.py")) if p not in skip for o in _offences(p)]
    assert bad == [], "old radius names (use radius / radius_x / radius_v):\n" + "\n".join(bad)


def test_the_checker_finds_old_names(tmp_path):
    p = tmp_path / "m.py"
    p.write_text("a = Wasserstein(theta=1)\nb = jdrkf.WassersteinDRKF(theta_x=1, radius_v=2)\nc = f.state_set.theta\n"
                 "d = self.theta_x\ne = KL(c=0.1)\n")
    assert len(_offences(p)) == 5


MAXENT = {
    "maxent_kl_solve": lambda **kw: jdrkf.sets.maxent_kl_solve(jnp.array([0.5, 0.3, 0.2]), **kw),
    "maxent_transport_solve": lambda **kw: jdrkf.sets.maxent_transport_solve(
        jnp.array([0.5, 0.5]), jnp.array([[0.0, 1.0, 2.0], [1.0, 0.0, 1.0]]), **kw),
    "maxent_wasserstein_continuous": lambda **kw: jdrkf.sets.maxent_wasserstein_continuous(
        jnp.array([0.5, 0.5]), jnp.array([[0.2, 0.2], [0.7, 0.6]]), key=jax.random.key(0), num_points=200, **kw),
}


@pytest.mark.parametrize("name", list(MAXENT))
def test_maxent_radius_and_its_deprecated_alias(name):
    """The max-entropy problems of Wang (2022) follow the rule: their budget is `radius`;
    `theta=` still works with a DeprecationWarning and gives the same solution."""
    new = MAXENT[name](radius=0.3)
    with pytest.warns(DeprecationWarning, match="radius="):
        old = MAXENT[name](theta=0.3)
    _same(new, old)
    with pytest.raises(TypeError, match="both"):
        MAXENT[name](radius=0.3, theta=0.3)
    with pytest.raises(ValueError, match="radius"):
        MAXENT[name](radius=-1.0)
