"""Contact solvers: cone projection, KKT conditions, independent solvers, PGS vs APGD, ADMM.

Units: forces N, velocities mm/s, Delassus matrices mm/(s·N).
"""

import functools
import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.optimize
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from jsnap._core.contact import (
    ContactSolution,
    implicit_solver,
    kkt_residual,
    kkt_terms,
    project_cone,
    solve_admm,
    solve_apgd,
    solve_pgs,
    solve_spg,
    symmetric_squeeze_problem,
)
from jsnap._core.contact.algorithms import _project_cone_split, _spd_inverse

# Kernel tests in float64 (jsnap's scoped 64-bit mode, as its entry points use internally).
pytestmark = pytest.mark.usefixtures("x64")

# Derandomised so that CI sees the same examples every run; few examples, since every one is a
# full solve. Solver functions are jitted once per shape (C = 8, C = 24) and shared.
PROPS = settings(
    derandomize=True,
    database=None,
    deadline=None,
    max_examples=25,
    suppress_health_check=[HealthCheck.too_slow],
)

TOL = 1e-6
TIGHT = 1e-10  # for comparisons with exact or independent solutions

# Compilation dominates this file's run time, so every solver is compiled once per shape: tol
# and gamma0 are traced arguments, always passed (zeros = cold start).
_apgd_jit = jax.jit(functools.partial(solve_apgd, max_iters=20000))
_pgs_jit = jax.jit(functools.partial(solve_pgs, max_iters=1000))
_admm_jit = jax.jit(functools.partial(solve_admm, max_iters=20000))
_spg_jit = jax.jit(functools.partial(solve_spg, max_iters=20000))
_project = jax.jit(project_cone)  # eager JAX dispatches op by op: seconds per call


def apgd(W, q, mu, mask, tol=TOL, gamma0=None):
    """APGD, at most 20000 iterations (degenerate problems at TIGHT need ~10⁴)."""
    gamma0 = np.zeros((len(mu), 3)) if gamma0 is None else gamma0
    return _apgd_jit(W, q, mu, mask, tol=tol, gamma0=gamma0)


def pgs(W, q, mu, mask, tol=TOL, gamma0=None):
    """PGS, at most 1000 sweeps."""
    gamma0 = np.zeros((len(mu), 3)) if gamma0 is None else gamma0
    return _pgs_jit(W, q, mu, mask, tol=tol, gamma0=gamma0)


def admm(W, q, mu, mask, tol=TOL, gamma0=None):
    """ADMM, at most 20000 iterations."""
    gamma0 = np.zeros((len(mu), 3)) if gamma0 is None else gamma0
    return _admm_jit(W, q, mu, mask, tol=tol, gamma0=gamma0)


def spg(W, q, mu, mask, tol=TOL, gamma0=None):
    """SPG, at most 20000 iterations."""
    gamma0 = np.zeros((len(mu), 3)) if gamma0 is None else gamma0
    return _spg_jit(W, q, mu, mask, tol=tol, gamma0=gamma0)


SOLVE = {"apgd": apgd, "admm": admm, "spg": spg}  # the shared compiled solves, by name


@jax.jit
def _kkt(W, q, mu, mask, gamma):
    return kkt_residual(W, q, mu, mask, gamma), kkt_terms(W, q, mu, mask, gamma)


def residual(W, q, mu, mask, gamma):
    return float(_kkt(W, q, mu, mask, gamma)[0])


def terms(W, q, mu, mask, gamma):
    return tuple(float(t) for t in _kkt(W, q, mu, mask, gamma)[1])


def random_problem(seed, C, n_kind, frictionless=False):
    """A physical random contact problem with C slots (NumPy float64).

    ``W = J A⁻¹ Jᵀ``: ``n`` generalised DoF with a random SPD mass-like matrix ``A``
    (eigenvalues over two decades) and a random contact Jacobian ``J`` (3C × n). ``n < 3C``
    makes W singular (more contact directions than DoF: redundant contacts). ``q = J v + s``:
    the relative velocity of a free velocity ``v`` plus a gap term ``s`` that only adds positive
    normal velocity (contacts within the margin but not yet touching). Keeping ``q`` in
    ``range(J)`` up to such gaps keeps the problem bounded when W is singular.
    """
    rng = np.random.default_rng(seed)
    n = {"tiny": 3, "under": C, "square": 3 * C, "over": 3 * C + 10}[n_kind]
    J = rng.standard_normal((3 * C, n))
    Q, _ = np.linalg.qr(rng.standard_normal((n, n)))
    Ainv = (Q / 10 ** rng.uniform(0, 2, n)) @ Q.T
    W = J @ Ainv @ J.T * 10 ** rng.uniform(-2, 2)
    W = 0.5 * (W + W.T)
    q = (J @ rng.standard_normal(n) * 10 ** rng.uniform(-1, 2)).reshape(C, 3)
    gaps = rng.random(C) < 0.3
    q[:, 0] += gaps * rng.uniform(0, 1, C) * np.abs(q).max()
    mu = rng.uniform(0, 1.2, C)
    mu[rng.random(C) < 0.2] = 0.0
    if frictionless:
        mu[:] = 0.0
    mask = rng.random(C) < rng.uniform(0.3, 1.0)
    return W, q.reshape(-1), mu, mask


def objective(W, q, gamma):
    g = np.asarray(gamma, np.float64).reshape(-1)
    return 0.5 * g @ W @ g + q @ g


seeds = st.integers(0, 2**31 - 1)
n_kinds = st.sampled_from(["tiny", "under", "square", "over"])


# ----------------------------------------------------------------------------------------------
# Cone projection


def _vectors_and_mu(draw_n=16):
    vec = hnp.arrays(np.float64, (draw_n, 3), elements=st.floats(-10, 10, width=64))
    mus = hnp.arrays(np.float64, (draw_n,), elements=st.one_of(st.just(0.0), st.floats(0, 1.2, width=64)))
    return vec, mus


@PROPS
@given(*_vectors_and_mu())
def test_project_cone_moreau(x, mu):
    """Moreau: x = p + r with p ∈ F, r ∈ F° (the polar cone), p ⊥ r; and P(P(x)) = P(x)."""
    # Exact zeros in the tangents exercise the ‖t‖ = 0 branch.
    x[::5, 1:] = 0.0
    p = np.asarray(_project(x, mu))
    r = x - p
    scale = 1 + np.abs(x).max()
    eps = 1e-12 * scale
    assert np.all(np.linalg.norm(p[:, 1:], axis=1) <= mu * p[:, 0] + eps)
    assert np.all(p[:, 0] >= -eps)  # F holds no pull, at mu = 0 too
    assert np.all(mu * np.linalg.norm(r[:, 1:], axis=1) <= -r[:, 0] + eps)
    assert np.all(np.abs(np.sum(p * r, axis=1)) <= 1e-12 * scale**2)
    np.testing.assert_allclose(np.asarray(_project(p, mu)), p, atol=eps)
    # Nothing in F is closer: compare with random points of the cone.
    rng = np.random.default_rng(0)
    n = rng.uniform(0, 10, (8, len(mu)))
    ang = rng.uniform(0, 2 * np.pi, (8, len(mu)))
    rad = mu * n * rng.uniform(0, 1, (8, len(mu)))
    cand = np.stack([n, rad * np.cos(ang), rad * np.sin(ang)], axis=-1)
    d_cand = np.linalg.norm(cand - x, axis=-1)
    assert np.all(np.linalg.norm(r, axis=1) <= d_cand + eps)


def test_project_cone_known_values():
    mu = np.array([0.5, 0.5, 0.5, 0.0, 0.0, 1.0, 0.0])
    x = np.array(
        [
            [2.0, 0.6, 0.8],  # inside (‖t‖ = 1 ≤ 1): kept
            [-2.0, 0.6, 0.8],  # in the polar cone (0.5 ≤ 2): apex
            [0.0, 3.0, 4.0],  # on neither: surface, n' = (0 + 2.5)/1.25 = 2, t' = 0.5·2·(0.6,0.8)
            [1.5, 3.0, -1.0],  # μ = 0: normal half-line
            [-1.5, 3.0, -1.0],
            [0.0, 0.0, 0.0],  # apex
            [-1.5, 0.0, 0.0],  # μ = 0, a pull with no tangential part (‖t‖ = 0 = μ n): apex
        ]
    )
    expect = np.array(
        [
            [2.0, 0.6, 0.8],
            [0.0, 0.0, 0.0],
            [2.0, 0.6, 0.8],
            [1.5, 0.0, 0.0],
            [0.0, 0.0, 0.0],
            [0.0, 0.0, 0.0],
            [0.0, 0.0, 0.0],
        ]
    )
    np.testing.assert_allclose(np.asarray(_project(x, mu)), expect, atol=1e-15)
    # The split form the solvers' inner loops use (n, t1, t2 apart) agrees.
    split = jax.jit(_project_cone_split)(*(jnp.asarray(x[:, k]) for k in range(3)), jnp.asarray(mu))
    np.testing.assert_allclose(np.stack([np.asarray(a) for a in split], axis=1), expect, atol=1e-15)


_JACOBIANS = [jax.jit(jac(project_cone, argnums=(0, 1))) for jac in (jax.jacfwd, jax.jacrev)]


@pytest.mark.parametrize(
    "x, mu",
    [
        ([0.0, 0.0, 0.0], 0.5),  # apex
        ([0.0, 0.0, 0.0], 0.0),  # apex, μ = 0
        ([1.0, 0.0, 0.0], 0.5),  # on the axis (‖t‖ = 0)
        ([-1.0, 0.0, 0.0], 0.5),  # on the negative axis
        ([1.0, 0.0, 0.0], 0.0),
        ([1.0, 2.0, -1.0], 0.0),  # μ = 0 with tangential part
        ([1.0, 0.3, 0.4], 0.5),  # on the cone's surface
        ([-1.0, 1.2, 1.6], 0.5),  # on the polar cone's surface
    ],
)
def test_project_cone_gradients_finite(x, mu):
    x = jnp.asarray(x)
    mu = jnp.asarray(mu)
    for jac in _JACOBIANS:
        dx, dmu = jac(x, mu)
        assert np.all(np.isfinite(dx)) and np.all(np.isfinite(dmu))


# ----------------------------------------------------------------------------------------------
# KKT residual


def _exact_kkt_problem(mu=0.4):
    """A problem built from a known solution: each contact separating, sticking or sliding."""
    rng = np.random.default_rng(3)
    C = 8
    B = rng.standard_normal((3 * C, 3 * C))
    W = B @ B.T / (3 * C) + 0.1 * np.eye(3 * C)
    gamma = np.zeros((C, 3))
    u = np.zeros((C, 3))
    for i in range(C):
        e = rng.standard_normal(2)
        e /= np.linalg.norm(e)
        kind = i % 3
        if kind == 0:  # separating: γ = 0, u inside the dual cone
            u[i] = [2.0, *(0.5 / mu * e)]
        elif kind == 1:  # sticking: γ inside the cone, u = 0
            gamma[i] = [1.5, *(0.3 * mu * 1.5 * e)]
        else:  # sliding: γ on the cone, u on the dual cone's surface opposite to γ_t
            gamma[i] = [1.2, *(mu * 1.2 * e)]
            u[i] = [mu * 0.7, *(-0.7 * e)]
    q = u.reshape(-1) - W @ gamma.reshape(-1)
    return W, q, np.full(C, mu), np.ones(C, bool), gamma


def test_kkt_residual_zero_at_exact_solution_and_found_by_apgd():
    W, q, mu, mask, gamma = _exact_kkt_problem()
    assert residual(W, q, mu, mask, gamma) < 1e-14
    assert max(terms(W, q, mu, mask, gamma)) < 1e-14
    sol = apgd(W, q, mu, mask, tol=TIGHT)
    np.testing.assert_allclose(np.asarray(sol.gamma), gamma, atol=1e-8)
    # A perturbed γ is not a solution.
    assert residual(W, q, mu, mask, gamma * 1.01) > 1e-4


@PROPS
@given(seeds, st.floats(-6, 6), st.floats(-6, 6))
def test_kkt_residual_scale_invariant(seed, log_a, log_b):
    """W → aW, q → bq scales the solution by b/a and leaves the residual unchanged."""
    W, q, mu, mask = random_problem(seed, 8, "square")
    mask[0] = True
    gamma = np.asarray(apgd(W, q, mu, mask).gamma) * 1.1 + 0.01  # not a solution
    a, b = 10.0**log_a, 10.0**log_b
    r1 = residual(W, q, mu, mask, gamma)
    r2 = residual(a * W, b * q, mu, mask, gamma * b / a)
    assert r1 > 0
    np.testing.assert_allclose(r2, r1, rtol=1e-9)


# ----------------------------------------------------------------------------------------------
# APGD on random physical problems


@PROPS
@given(seeds, st.sampled_from([8, 24]), n_kinds)
def test_apgd_satisfies_kkt(seed, C, n_kind):
    W, q, mu, mask = random_problem(seed, C, n_kind)
    sol = apgd(W, q, mu, mask)
    assert 0 <= int(sol.iterations) < 3000
    _assert_solves(W, q, mu, mask, sol)


def _assert_solves(W, q, mu, mask, sol):
    """``sol`` converged: its KKT residual (recomputed) within TOL, its forces feasible, and the
    separate KKT terms of the residual's order.

    The natural residual bounds the other terms only up to a problem-dependent factor (Moreau:
    ``γ·u/L = r·(γ − p°)``, with ``r`` the residual vector and ``p°`` the polar part of
    ``γ − u/L``). Measured over 1200 random problems each (seeds 0-149 and 100000, C = 8 and 24,
    every kind): dual ≤ 1.50 TOL for both solvers; complementarity up to 2.10 TOL
    (APGD) and 2.27 TOL (ADMM), 1 and 3 of them above 2 TOL. Hence 3 TOL for it."""
    assert bool(sol.converged)
    gamma = np.asarray(sol.gamma)
    # Inactive slots are exactly zero, whatever W and q hold there.
    assert np.all(gamma[~mask] == 0.0)
    r = residual(W, q, mu, mask, gamma)
    assert r <= TOL
    np.testing.assert_allclose(float(sol.residual), r, rtol=1e-9, atol=1e-300)
    primal, dual, comp = terms(W, q, mu, mask, gamma)
    assert primal <= 1e-14  # iterates are projections: feasible up to round-off
    assert dual <= 2 * TOL
    assert comp <= 3 * TOL


@PROPS
@given(seeds, n_kinds)
def test_frictionless_matches_active_set_enumeration(seed, n_kind):
    """μ = 0: the normal LCP solved exactly by enumerating supports (C = 8: ≤ 256 of them).

    For W ⪰ 0 some solution has a support S with W_SS nonsingular (move along a null vector
    of W_SS until a force hits zero), so enumeration finds it. γ itself need not be unique
    when W is singular; the objective and the velocity u = Wγ + q are.
    """
    W, q, mu, mask = random_problem(seed, 8, n_kind, frictionless=True)
    act = np.flatnonzero(mask)
    Wn = W[0::3, 0::3][np.ix_(act, act)]
    qn = q[0::3][act]
    qscale = np.abs(qn).max() if len(act) else 1.0
    best = None
    for r in range(len(act) + 1):
        for S in map(list, itertools.combinations(range(len(act)), r)):
            x = np.zeros(len(act))
            if S:
                x[S] = np.linalg.lstsq(Wn[np.ix_(S, S)], -qn[S], rcond=None)[0]
            u = Wn @ x + qn
            if (
                x.min(initial=0) >= -1e-12 * (1 + np.abs(x).max(initial=0))
                and u.min(initial=0) >= -1e-9 * qscale
            ):
                f = 0.5 * x @ Wn @ x + qn @ x
                if best is None or f < best[0]:
                    best = (f, u)
    assert best is not None
    sol = apgd(W, q, mu, mask, tol=TIGHT)
    assert bool(sol.converged)
    gamma = np.asarray(sol.gamma)
    assert np.all(gamma[:, 1:] == 0.0)
    f = objective(W, q, gamma)
    assert abs(f - best[0]) <= 1e-9 * abs(best[0]) + 1e-300
    u = (W @ gamma.reshape(-1) + q)[0::3][act]
    np.testing.assert_allclose(u, best[1], atol=1e-5 * qscale)


@settings(PROPS, max_examples=8)
@given(seeds, st.sampled_from(["under", "square", "over"]))
def test_friction_objective_not_worse_than_slsqp(seed, n_kind):
    """With friction, APGD's objective is ≤ that of SciPy's SLSQP on the same convex problem."""
    W, q, mu, mask = random_problem(seed, 8, n_kind)
    C = 8

    def fun(g):
        return 0.5 * g @ W @ g + q @ g, W @ g + q

    def cone(g):  # μ²γ_n² − ‖γ_t‖² ≥ 0 together with γ_n ≥ 0 (a bound) is the cone
        g = g.reshape(C, 3)
        return (mu**2 * g[:, 0] ** 2 - g[:, 1] ** 2 - g[:, 2] ** 2)[mask]

    def cone_jac(g):
        g = g.reshape(C, 3)
        Jc = np.zeros((C, C, 3))
        Jc[np.arange(C), np.arange(C)] = np.stack([2 * mu**2 * g[:, 0], -2 * g[:, 1], -2 * g[:, 2]], 1)
        return Jc.reshape(C, 3 * C)[mask]

    bounds = []
    for i in range(C):
        if not mask[i]:
            bounds += [(0, 0)] * 3
        elif mu[i] == 0:
            bounds += [(0, None), (0, 0), (0, 0)]
        else:
            bounds += [(0, None), (None, None), (None, None)]
    x0 = np.tile([1.0, 0.0, 0.0], C) * np.repeat(mask, 3)
    res = scipy.optimize.minimize(
        fun,
        x0,
        jac=True,
        method="SLSQP",
        bounds=bounds,
        constraints=[{"type": "ineq", "fun": cone, "jac": cone_jac}] if mask.any() else [],
        options={"maxiter": 1000, "ftol": 1e-14},
    )
    # SLSQP may end slightly outside the cone, where the objective can be lower than the
    # minimum: compare with the objective at its projection onto the cones (a feasible point).
    x = np.asarray(_project(res.x.reshape(C, 3), mu))
    assert np.all(np.linalg.norm(x[:, 1:], axis=1) <= mu * x[:, 0] * (1 + 1e-12))
    sol = apgd(W, q, mu, mask, tol=TIGHT)
    assert bool(sol.converged)
    f_apgd = objective(W, q, sol.gamma)
    scale = np.abs(q).max() * max(np.abs(x).max(), np.abs(np.asarray(sol.gamma)).max())
    assert f_apgd <= objective(W, q, x) + 1e-9 * scale


# ----------------------------------------------------------------------------------------------
# PGS: correct where it should be, stalling on the squeeze


def _separated_problem(seed=0, C=8):
    """Weakly coupled contacts (diagonally dominant W): PGS's home ground."""
    rng = np.random.default_rng(seed)
    B = 0.1 * rng.standard_normal((3 * C, 3 * C))
    W = np.eye(3 * C) + B @ B.T / (3 * C)
    q = rng.standard_normal(3 * C)
    q[0::3] -= 0.5
    mu = rng.uniform(0, 1, C)
    mask = np.arange(C) != 5
    return W, q, mu, mask


def test_pgs_converges_to_apgd_solution_on_well_conditioned_problem():
    W, q, mu, mask = _separated_problem()
    p = pgs(W, q, mu, mask)
    a = apgd(W, q, mu, mask, tol=TIGHT)
    assert bool(p.converged) and int(p.iterations) < 50
    assert np.all(np.asarray(p.gamma)[~mask] == 0.0)
    np.testing.assert_allclose(np.asarray(p.gamma), np.asarray(a.gamma), atol=1e-5)
    # Tight tolerance: PGS reaches the same point as APGD to high accuracy.
    p = pgs(W, q, mu, mask, tol=TIGHT)
    assert bool(p.converged)
    np.testing.assert_allclose(np.asarray(p.gamma), np.asarray(a.gamma), atol=1e-8)


def test_symmetric_squeeze_pgs_stalls_apgd_converges():
    """The paper's counter-example.

    A light rigid plug (~80 mg, translating freely) is squeezed between two identical stiff
    latches; 4 contact points on each hook's lead ramp (a line across the width), normals +x on
    the left hook and −x on the right, μ = 0.3; the hooks close on the plug at 10 mm/s while
    the plug slides down at 10 mm/s. Over one 1 ms PMI step the plug's mobility is 300× a
    hook's (``mobility_ratio``), so ``W = W_hooks + (dt/2m) G Gᵀ`` has a huge rank-3 part: any
    imbalance between left and right forces moves the plug fast, while the squeezing forces
    that actually develop are resisted only by the hooks. Gauss–Seidel, updating one contact at
    a time, overshoots through the plug and must shuttle force back and forth between the hooks;
    APGD moves all contacts together along the gradient.
    """
    P = symmetric_squeeze_problem(n_per_side=4, mobility_ratio=300.0, mu=0.3)
    assert P.condition > 1e4  # genuinely ill-conditioned
    assert 5e-8 < P.plug_mass < 2e-7  # t: 0.05 to 0.2 g
    a = apgd(P.W, P.q, P.mu, P.mask)
    p = pgs(P.W, P.q, P.mu, P.mask)  # cap: 1000 sweeps
    # Measured: APGD converges in 362 iterations; PGS after 1000 sweeps is at ~1.6e-4.
    assert bool(a.converged)
    assert int(a.iterations) <= 500
    assert not bool(p.converged)
    assert int(p.iterations) == 1000
    assert float(p.residual) >= 100 * TOL
    assert float(p.residual) >= 100 * float(a.residual)

    # The physics of the converged answer (tight solve): the plug is in balance, the two hooks
    # carry mirror-image forces, and friction holds the light plug (sticking, inside the cone).
    g = np.asarray(apgd(P.W, P.q, P.mu, P.mask, tol=TIGHT).gamma)[P.mask]
    left, right = g[:4], g[4:]
    np.testing.assert_allclose(left, right, rtol=1e-6, atol=1e-9)
    assert np.all(left[:, 0] > 0)
    net_x = left[:, 0].sum() - right[:, 0].sum()
    assert abs(net_x) <= 1e-8 * left[:, 0].sum()
    assert np.all(np.linalg.norm(g[:, 1:], axis=1) < 0.3 * g[:, 0])


# ----------------------------------------------------------------------------------------------
# ADMM and SPG: the same solutions as APGD, by independent iterations


@pytest.mark.parametrize("solver", ["admm", "spg"])
@settings(PROPS, max_examples=12)
@given(seed=seeds, C=st.sampled_from([8, 24]), n_kind=n_kinds)
def test_admm_and_spg_satisfy_kkt_and_agree_with_apgd(solver, seed, C, n_kind):
    """ADMM and SPG meet the tolerance on the KKT residual with feasible forces; solved
    tightly, they reach APGD's objective and contact velocities (γ itself need not be unique
    when W is singular; the objective and u = Wγ + q are)."""
    W, q, mu, mask = random_problem(seed, C, n_kind)
    other = SOLVE[solver]
    _assert_solves(W, q, mu, mask, other(W, q, mu, mask))
    a, d = apgd(W, q, mu, mask, tol=TIGHT), other(W, q, mu, mask, tol=TIGHT)
    assert bool(a.converged) and bool(d.converged)
    fa, fd = objective(W, q, a.gamma), objective(W, q, d.gamma)
    scale = np.abs(q).max() * max(np.abs(np.asarray(a.gamma)).max(), 1e-300)
    assert abs(fa - fd) <= 1e-8 * scale
    u = [W @ np.asarray(g.gamma).reshape(-1) + q for g in (a, d)]
    np.testing.assert_allclose(u[1][np.repeat(mask, 3)], u[0][np.repeat(mask, 3)], atol=1e-6 * np.abs(q).max())


@pytest.mark.parametrize("solver", ["admm", "spg"])
def test_admm_and_spg_on_the_symmetric_squeeze(solver):
    """The squeeze's ill-conditioning (cond(W) > 1e4) is what ADMM's (W + ρI)⁻¹ absorbs and
    SPG's spectral step follows: both converge in fewer iterations than APGD (measured to 1e-6:
    APGD 362, ADMM 254, SPG 64), to the same mirror-image forces."""
    P = symmetric_squeeze_problem(n_per_side=4, mobility_ratio=300.0, mu=0.3)
    other = SOLVE[solver]
    a, d = apgd(P.W, P.q, P.mu, P.mask), other(P.W, P.q, P.mu, P.mask)
    assert bool(d.converged)
    assert int(d.iterations) < int(a.iterations)
    # To 1e-12, not TIGHT: at 1e-10 APGD's and ADMM's velocities are still 1.5e-6 off (1.2e-7 of
    # q), SPG's 2.4e-8 (measured); at 1e-12 all three are within 1.5e-8.
    ref = np.asarray(apgd(P.W, P.q, P.mu, P.mask, tol=1e-12).gamma)
    g = np.asarray(other(P.W, P.q, P.mu, P.mask, tol=1e-12).gamma)
    # W is singular here, so only W γ (the velocities) and what it fixes are unique: the normal
    # forces, and the tangential ones up to a null-space share (1e-8 N of 2e-4 N measured).
    u = [P.W @ x.reshape(-1) + P.q for x in (ref, g)]
    np.testing.assert_allclose(u[1], u[0], rtol=0, atol=1e-7 * np.abs(P.q).max())
    np.testing.assert_allclose(g[:, 0], ref[:, 0], rtol=1e-6)
    left, right = g[P.mask][:4], g[P.mask][4:]
    np.testing.assert_allclose(left, right, rtol=1e-6, atol=1e-9)


@pytest.mark.parametrize("n", [1, 9, 36, 72, 149, 192])
def test_spd_inverse_against_numpy(n):
    """Gauss-Jordan sweeps (n <= 48) and the recursive block inverse above (149: uneven splits
    over two levels), against NumPy; under vmap the same as one matrix at a time."""
    rng = np.random.default_rng(n)
    B = rng.standard_normal((n, n + 2))
    A = B @ B.T / n + 1e-3 * np.eye(n)  # condition number up to ~1e4
    X = np.asarray(jax.jit(_spd_inverse)(A))
    np.testing.assert_allclose(X, np.linalg.inv(A), rtol=1e-9 * np.linalg.cond(A), atol=0)
    np.testing.assert_allclose(X, X.T, rtol=0, atol=1e-12 * np.abs(X).max())
    batched = np.asarray(jax.jit(jax.vmap(_spd_inverse))(np.stack([A, 2 * A])))
    np.testing.assert_allclose(batched[0], X, rtol=0, atol=1e-12 * np.abs(X).max())
    np.testing.assert_allclose(batched[1], X / 2, rtol=0, atol=1e-12 * np.abs(X).max())


# ----------------------------------------------------------------------------------------------
# JAX behaviour: vmap, jit, dtypes, warm start, gradients, errors


@pytest.mark.parametrize("solver", ["apgd", "admm", "spg"])
def test_vmap_equals_loop_and_no_recompile(solver):
    """A batch solves each problem as one solve does. With W regular ("square") the solution is
    unique and the iterates are the same up to round-off. With W singular ("under", redundant
    contacts) the solution set is a face: vmap's reductions round differently, and a method
    whose steps adapt to the iterate (SPG's Barzilai-Borwein steps) may then settle on another
    point of it; both must still solve the problem, with the same objective."""
    kinds = ((0, "square"), (1, "square"), (2, "under"), (3, "under"))
    problems = [random_problem(s, 8, kind) for s, kind in kinds]
    W, q, mu, mask = (np.stack(a) for a in zip(*problems, strict=True))
    jitted = {"apgd": (solve_apgd, _apgd_jit), "admm": (solve_admm, _admm_jit), "spg": (solve_spg, _spg_jit)}
    f, one_jit = jitted[solver]
    batched = jax.jit(jax.vmap(functools.partial(f, max_iters=3000, tol=TOL)))(W, q, mu, mask)
    assert batched.gamma.shape == (4, 8, 3) and batched.iterations.shape == (4,)
    solve_one = SOLVE[solver]
    for i, p in enumerate(problems):
        one = solve_one(*p)
        sol = jax.tree_util.tree_map(lambda a, i=i: a[i], batched)
        _assert_solves(*p, sol)
        if i < 2:
            np.testing.assert_allclose(np.asarray(sol.gamma), np.asarray(one.gamma), atol=1e-9)
            assert int(sol.iterations) == int(one.iterations)
        else:
            fa, fb = objective(p[0], p[1], sol.gamma), objective(p[0], p[1], one.gamma)
            assert abs(fa - fb) <= 1e-6 * abs(fb)
    n_compiled = one_jit._cache_size()
    solve_one(*problems[1])
    assert one_jit._cache_size() == n_compiled


@pytest.mark.parametrize("solver", ["apgd", "pgs", "admm", "spg"])
def test_while_loop_takes_the_frozen_scans_iterates(solver):
    """The forward-only solve (``differentiable=False``: a while loop of two steps per trip)
    stops where the differentiable frozen scan freezes, with the same iterate: converged, and
    cut by an odd or even cap (the loop's last trip then has a step past the cap, frozen)."""
    f = {"apgd": solve_apgd, "pgs": solve_pgs, "admm": solve_admm, "spg": solve_spg}[solver]
    problems = [random_problem(s, 8, kind) for s, kind in ((11, "under"), (12, "square"), (13, "over"))]
    for cap in (1, 6, 7, 400):
        loop = jax.jit(functools.partial(f, max_iters=cap, tol=TOL, differentiable=False))
        scan = jax.jit(functools.partial(f, max_iters=cap, tol=TOL, differentiable=True))
        for p in problems:
            a, b = loop(*p), scan(*p)
            assert int(a.iterations) == int(b.iterations) <= cap
            assert bool(a.converged) == bool(b.converged)
            np.testing.assert_allclose(np.asarray(a.gamma), np.asarray(b.gamma), rtol=1e-12, atol=1e-12)
    assert int(a.iterations) < 400 and bool(a.converged)  # the last problem converged within the cap


@pytest.mark.parametrize("solver", ["apgd", "pgs", "admm", "spg"])
def test_float32_in_float32_out(solver):
    W, q, mu, mask = _separated_problem()
    f = {"apgd": solve_apgd, "pgs": solve_pgs, "admm": solve_admm, "spg": solve_spg}[solver]
    fn = jax.jit(functools.partial(f, max_iters=500, tol=1e-5))
    sol32 = fn(W.astype(np.float32), q.astype(np.float32), mu.astype(np.float32), mask)
    assert isinstance(sol32, ContactSolution)
    assert sol32.gamma.dtype == jnp.float32 and sol32.residual.dtype == jnp.float32
    assert sol32.iterations.dtype == jnp.int32 and sol32.converged.dtype == jnp.bool_
    assert bool(sol32.converged)
    ref = np.asarray(apgd(W, q, mu, mask, tol=TIGHT).gamma)
    np.testing.assert_allclose(np.asarray(sol32.gamma), ref, atol=1e-4)


def test_warm_start_from_solution_takes_no_iterations():
    W, q, mu, mask = random_problem(7, 8, "square")
    sol = apgd(W, q, mu, mask)
    warm = apgd(W, q, mu, mask, gamma0=sol.gamma)
    assert int(warm.iterations) == 0 and bool(warm.converged)
    # The warm start is re-projected onto the cones: equal up to round-off.
    np.testing.assert_allclose(np.asarray(warm.gamma), np.asarray(sol.gamma), rtol=1e-12)
    # Garbage in inactive slots of the warm start is discarded.
    g0 = np.asarray(sol.gamma).copy()
    g0[~mask] = 5.0
    warm = pgs(W, q, mu, mask, gamma0=g0)
    assert np.all(np.asarray(warm.gamma)[~mask] == 0.0)
    # ADMM: its multiplier starts at the one that makes the warm start a fixed point.
    warm = admm(W, q, mu, mask, gamma0=g0)
    assert int(warm.iterations) == 0 and bool(warm.converged)
    assert np.all(np.asarray(warm.gamma)[~mask] == 0.0)
    warm = spg(W, q, mu, mask, gamma0=g0)
    assert int(warm.iterations) == 0 and bool(warm.converged)
    assert np.all(np.asarray(warm.gamma)[~mask] == 0.0)


@pytest.mark.parametrize("solver", ["apgd", "admm", "spg"])
def test_gradient_through_the_solver_matches_finite_differences(solver):
    """d(weighted forces)/dq through the unrolled, frozen scan (ADMM: and its inverse's sweeps;
    SPG: implicitly, the only way a scene may differentiate it), against central differences of
    APGD's solutions.

    The problem has strict complementarity (separating, sticking and sliding contacts with
    margins), so the solution is smooth in q near this point.
    """
    W, q, mu, mask, _ = _exact_kkt_problem()
    w = np.random.default_rng(1).standard_normal((8, 3))
    solve = {"apgd": solve_apgd, "admm": solve_admm, "spg": implicit_solver(solve_spg)}[solver]

    def f(q, mu):
        return jnp.sum(solve(W, q, mu, mask, max_iters=1000, tol=1e-13).gamma * w)

    gq, gmu = jax.jit(jax.grad(f, argnums=(0, 1)))(q, mu)
    assert np.all(np.isfinite(gq)) and np.all(np.isfinite(gmu))

    def fj(q, mu):  # the same solve through the shared compiled function
        return float(np.sum(np.asarray(apgd(W, q, mu, mask, tol=1e-13).gamma) * w))

    rng = np.random.default_rng(2)
    for _ in range(2):
        d = rng.standard_normal(q.shape)
        h = 1e-5
        fd = (fj(q + h * d, mu) - fj(q - h * d, mu)) / (2 * h)
        np.testing.assert_allclose(float(gq @ d), float(fd), rtol=1e-5)
    dm = rng.standard_normal(mu.shape)
    fd = (fj(q, mu + h * dm) - fj(q, mu - h * dm)) / (2 * h)
    np.testing.assert_allclose(float(gmu @ dm), float(fd), rtol=1e-5)


def test_shape_errors_name_the_argument():
    W, q, mu, mask = _separated_problem()
    with pytest.raises(ValueError, match=r"W must be \(3C, 3C\)"):
        solve_apgd(W[:-1], q, mu, mask, max_iters=10, tol=TOL)
    with pytest.raises(ValueError, match="q must be"):
        solve_pgs(W, q[:-1], mu, mask, max_iters=10, tol=TOL)
    with pytest.raises(ValueError, match="mu must be"):
        kkt_residual(W, q, mu[:-1], mask, np.zeros((8, 3)))
    with pytest.raises(ValueError, match="mask must be"):
        solve_apgd(W, q, mu, mask[:-1], max_iters=10, tol=TOL)
    with pytest.raises(ValueError, match="max_iters must be a positive"):
        solve_apgd(W, q, mu, mask, max_iters=0, tol=TOL)
    with pytest.raises(ValueError, match="gamma0 must be"):
        solve_apgd(W, q, mu, mask, max_iters=10, tol=TOL, gamma0=np.zeros((7, 3)))


@pytest.mark.parametrize("n_active", [5, 50, 100])
def test_solve_on_leading_slots_is_the_whole_buffers(n_active, x64):
    """A step solves its cone problem on the smallest leading part of the contact buffer that
    holds every active slot (a quarter, half or all of 128 slots), forming the operator and the
    velocity change for those slots only: inactive slots enter only as zero rows and columns of
    W, so the forces and the velocity change are those of the solve on the whole buffer."""
    from types import SimpleNamespace

    from jsnap._core.contact import APGD
    from jsnap._core.step import ContactProblem, _buckets, _solve

    C, n = 128, 40
    assert _buckets(C) == (32, 64, 128) and _buckets(64) == (16, 64)
    assert _buckets(256) == (16, 24, 32, 48, 64, 128, 256)
    W, q, mu, _ = random_problem(seed=n_active, C=C, n_kind="over")
    A = np.random.default_rng(n_active).standard_normal((C, 3, n))  # what contact_velocity applies

    class Part:
        """A part whose contact operator for the slots ``idx`` is W's rows and columns there."""

        factored = False

        def contact_operator(self, op, idx):
            return jnp.asarray(A)[idx], jnp.asarray(W.reshape(C, 3, C, 3))[idx][:, :, idx]

        def contact_velocity(self, op, A_k, force):
            return jnp.einsum("cdn,cd->n", A_k, force)

    active = np.arange(C) < n_active  # the buffer fills from the front (top_k)
    prob = ContactProblem(
        shift=jnp.asarray(0.0),
        q=jnp.asarray(q),
        mu=jnp.asarray(mu),
        active=jnp.asarray(active),
        idx=jnp.arange(C),
        R=jnp.broadcast_to(jnp.eye(3), (C, 3, 3)),
        points=jnp.zeros((C, 3)),
        s_p=jnp.asarray(0.0),
        gamma0=jnp.zeros((C, 3)),
        overflow=jnp.asarray(0),
    )
    solver = APGD(max_iters=20000, tol=1e-12)
    model = SimpleNamespace(contact=SimpleNamespace(solver=solver), part=Part())
    part, Gamma, dv = _solve(model, None, prob)
    whole = solver.solve(jnp.asarray(W), jnp.asarray(q), jnp.asarray(mu), jnp.asarray(active))
    assert bool(part.converged) and bool(whole.converged)
    scale = float(jnp.abs(whole.gamma).max())
    assert scale > 0
    np.testing.assert_allclose(np.asarray(Gamma), np.asarray(whole.gamma), atol=1e-7 * scale)
    assert not np.any(np.asarray(Gamma)[~active])
    dv_whole = np.einsum("cdn,cd->n", A, np.asarray(whole.gamma))
    np.testing.assert_allclose(np.asarray(dv), dv_whole, atol=1e-7 * np.abs(dv_whole).max())
