"""Frictional contact: the cone complementarity problem and its solvers.

Units: forces ``gamma`` in N, velocities ``q``/``u`` in mm/s, the Delassus operator ``W`` in
mm/(s·N) (a velocity per unit force: ``W = J S⁻¹ Jᵀ`` for the PMI midpoint velocity).

For ``C`` contact slots, each with a local frame (normal ``n``, tangents ``t1``, ``t2``), the
unknown is ``gamma`` (C, 3) = ``[gamma_n, gamma_t1, gamma_t2]`` per contact. Flattened vectors
are contact-major: entry ``3i + 0`` is contact ``i``'s normal, ``3i + 1`` and ``3i + 2`` its
tangents. The problem (velocity-level Signorini with Coulomb friction by maximal dissipation, in
its convex form) is

    min_gamma  ½ gammaᵀ W gamma + gammaᵀ q
    s.t.       gamma_i ∈ F_i = {‖gamma_t‖ ≤ mu_i gamma_n}   (active slots)
               gamma_i = 0                                  (inactive slots)

with contact velocity ``u = W gamma + q``. Its KKT conditions: ``gamma_i ∈ F_i``,
``u_i ∈ F_i* = {mu_i ‖u_t‖ ≤ u_n}`` (the dual cone) and ``gamma_i · u_i = 0``.

Solvers:

- ``solve_apgd``: accelerated projected gradient (Nesterov/FISTA) with the gradient-based
  adaptive restart of O'Donoghue & Candès, fixed step ``1/L``. The default.
- ``solve_admm``: ADMM with ``(W + ρI)⁻¹`` formed once per solve; fewer iterations than APGD on
  the ill-conditioned line contacts of the scenes (``contact.solver = "admm"``, opt-in).
- ``solve_spg``: spectral projected gradient (Barzilai–Borwein steps, non-monotone line search);
  fewer iterations than APGD on the same problems at the same cost per iteration
  (``contact.solver = "spg"``, opt-in; its derivatives are taken implicitly).
- ``solve_pgs``: projected block Gauss–Seidel, the classic baseline. It stalls on the
  ill-conditioned symmetric squeeze (a light plug between two hooks); it is kept to show that.

All run a ``jax.lax.scan`` of static length ``max_iters`` whose carry freezes (``lax.cond``)
once the residual reaches ``tol``: shapes and trip counts are static, so they jit, vmap and
reverse-differentiate (no ``while_loop``). Convergence is judged by ``kkt_residual``; read its
docstring before choosing ``tol``: on ill-conditioned problems 1e-6 is not a small force error.
"""

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jsnap._core.util import safe_norm

# Power iterations for the step size. W is small (3C ≤ a few hundred), so 50 matvecs cost
# about as much as 50 solver iterations; the estimate they give is a lower bound of ‖W‖, hence
# the safety factor (and the cap by the trace, a guaranteed upper bound). On 300 random problems
# with clustered top eigenvalues (3C = 12-192: low-rank Wishart, a top cluster over a bulk up to
# 0.99 of it, near-duplicate rows) the worst estimate was 0.864 ‖W‖ in float32 (0.945 in float64)
# before the factor, so L can be ~5 % short: a step ~5 % past FISTA's 1/‖W‖ (a projected-gradient
# step converges below 2/‖W‖, and the solver returns its best iterate by the residual). Lanczos
# with 10 steps and full reorthogonalisation is closer (worst 0.932) but not faster on the
# scenes' problems (the LAPACK eigensolver of its Ritz matrix and five small dots per step).
_POWER_ITERS = 50
_POWER_SAFETY = 1.1
# The power iteration stops once ‖Wv − ρv‖ ≤ _POWER_TOL ρ (ρ = vᵀWv, v the unit iterate): v is
# then an eigenvector to that tolerance, and ρ within it of an eigenvalue. The scenes' contact
# problems have one eigenvalue well above the rest (points of one stiff hook): there the
# iteration settles after 5-7 iterations, ‖W‖ the same to round-off, where the 50 cost ~7 % of a
# light reduced step. Clustered top eigenvalues keep the residual up (the iterate mixes their
# eigenvectors), so those problems still take the 50.
_POWER_TOL = 1e-3
# Solver iterations per block of the frozen scan (see _frozen_scan).
_BLOCK = 16
# Solver iterations per trip of the while loop (see _while). Measured (float32/64, 12 and 24
# slots of a default-scene problem, 200 iterations): 1.1-1.2x faster per iteration than one
# step per trip, and 3 or 4 no faster than 2; the reduced scene with light contact settings
# stepped at 311-333 against 443-505 µs (same forces; its rollout compiles as fast).
_UNROLL = 2
# ADMM's penalty, relative to the mean of W's diagonal over the free components, and its
# over-relaxation (solve_admm). Measured in float64 to the 1e-6 residual (docs/contact.md). On
# the recorded solves of three rollouts (default scene; 1344-dof reduced, default and light
# contact) a penalty fixed relative to L did well (0.003-0.005 L: 74-185 iterations on average,
# capped at 600) but took 500-1100 iterations on well-conditioned random problems (APGD: 20-60),
# which want a penalty ~0.1-0.3 L. Relative to the mean diagonal (0.02-0.04 L on the scenes'
# line contacts, 0.1-0.9 L on well-conditioned problems) one factor serves both: 0.2 gives 76-180
# iterations on average on the scene solves (APGD 249-582) and 48-80 on the random ones. α = 1.6
# and 1.8 took alike, both fewer than α = 1 (plain ADMM).
_ADMM_RHO = 0.2
_ADMM_RELAX = 1.6
# SPG's non-monotone memory (objective values the line search compares against), sufficient
# decrease constant and largest step (times 1/L; the BB step is ≥ 1/L by construction).
_SPG_MEMORY = 20
_SPG_DECREASE = 1e-4
_SPG_MAX_STEP = 1e6

__all__ = [
    "ContactSolution",
    "KKTTerms",
    "SqueezeProblem",
    "kkt_residual",
    "kkt_terms",
    "project_cone",
    "solve_admm",
    "solve_apgd",
    "solve_pgs",
    "solve_spg",
    "symmetric_squeeze_problem",
]


class ContactSolution(NamedTuple):
    """Result of a contact solve.

    Attributes:
        gamma: (C, 3) contact forces in the local frames ``[n, t1, t2]``, N. Inactive slots are
            exactly 0.
        iterations: int32 scalar, iterations (APGD) or sweeps (PGS) actually taken; equals
            ``max_iters`` when not converged, 0 when the warm start already met ``tol``.
        residual: scalar, ``kkt_residual`` of the returned ``gamma`` (dimensionless).
        converged: bool scalar, ``residual <= tol``.
    """

    gamma: jax.Array
    iterations: jax.Array
    residual: jax.Array
    converged: jax.Array


class KKTTerms(NamedTuple):
    """Separate, normalised KKT violations (all dimensionless, all 0 exactly at a solution).

    With the force scale ``s_f = ‖gamma‖_∞ + ‖q‖_∞ / L`` and the velocity scale
    ``s_v = L s_f = L ‖gamma‖_∞ + ‖q‖_∞`` (``L`` the estimate of ‖W‖ used by ``kkt_residual``),
    maxima over active contacts of:

    Attributes:
        primal: ``‖gamma_i − proj_{F_i}(gamma_i)‖ / s_f``, distance of the force to its cone.
        dual: ``‖proj_{F_i}(−u_i)‖ / s_v``, the distance of the velocity to the dual cone
            ``F_i*`` (Moreau: the polar of ``F_i*`` is ``−F_i``).
        complementarity: ``|gamma_i · u_i| / (s_f s_v)``.
    """

    primal: jax.Array
    dual: jax.Array
    complementarity: jax.Array


# ----------------------------------------------------------------------------------------------
# Cone projection


def project_cone(gamma, mu):
    """Euclidean projection onto the Coulomb friction cones ``F_i = {‖t‖ ≤ mu_i n}``.

    Closed form for a second-order cone scaled by ``mu``: inside the cone the point is kept; in
    the polar cone ``{mu ‖t‖ ≤ −n}`` it goes to the apex; otherwise onto the cone's surface,
    ``n' = (n + mu ‖t‖)/(1 + mu²)``, ``t' = mu n' t/‖t‖``. ``mu = 0`` gives the projection onto the
    normal half-line ``{t = 0, n ≥ 0}``.

    Values and gradients are NaN-free everywhere (apex, zero tangential part, ``mu = 0``): the
    norm is a safe norm and the division by ``‖t‖`` is double-``where`` guarded.

    Args:
        gamma: (..., 3) vectors ``[n, t1, t2]`` (any units; typically forces, N).
        mu: (...,) friction coefficients, ``mu ≥ 0`` (dimensionless).

    Returns:
        (..., 3) the projections, same dtype as ``gamma``.
    """
    gamma = jnp.asarray(gamma)
    mu = jnp.asarray(mu, dtype=gamma.dtype)
    n = gamma[..., 0]
    t = gamma[..., 1:]
    nt = safe_norm(t, axis=-1)
    # n >= 0 as well: at mu = 0 a pull with no tangential part (0 <= mu * n = -0.0) would pass.
    inside = (nt <= mu * n) & (n >= 0.0)
    to_apex = mu * nt <= -n
    n_surf = (n + mu * nt) / (1.0 + mu * mu)
    # On the surface branch ‖t‖ > 0 always (else the point is inside or in the polar cone), but
    # the branch is evaluated everywhere, so guard the division for the gradient's sake.
    direction = t / jnp.where(nt > 0, nt, 1.0)[..., None]
    t_surf = (mu * n_surf)[..., None] * direction
    out_n = jnp.where(inside, n, jnp.where(to_apex, 0.0, n_surf))
    out_t = jnp.where(inside[..., None], t, jnp.where(to_apex[..., None], 0.0, t_surf))
    return jnp.concatenate([out_n[..., None], out_t], axis=-1)


def _project_cone_split(n, t1, t2, mu):
    """``project_cone`` on the components given apart (each (C,)): the same arithmetic, all of
    it elementwise (no reduction over a length-3 axis), for the solvers' inner loops."""
    sq = t1 * t1 + t2 * t2
    ok = sq > 1e-30  # as safe_norm
    nt = jnp.where(ok, jnp.sqrt(jnp.where(ok, sq, 1.0)), 0.0)
    inside = (nt <= mu * n) & (n >= 0.0)  # as project_cone
    to_apex = mu * nt <= -n
    n_surf = (n + mu * nt) / (1.0 + mu * mu)
    scale = mu * n_surf / jnp.where(nt > 0, nt, 1.0)
    out_n = jnp.where(inside, n, jnp.where(to_apex, 0.0, n_surf))
    out_t1 = jnp.where(inside, t1, jnp.where(to_apex, 0.0, scale * t1))
    out_t2 = jnp.where(inside, t2, jnp.where(to_apex, 0.0, scale * t2))
    return out_n, out_t1, out_t2


# ----------------------------------------------------------------------------------------------
# Shared pieces


def _check_shapes(W, q, mu, mask, max_iters=None, gamma0=None):
    """Structural errors are raised at trace time, naming the argument."""
    if W.ndim != 2 or W.shape[0] != W.shape[1] or W.shape[0] % 3:
        raise ValueError(f"W must be (3C, 3C), got shape {W.shape}")
    c = W.shape[0] // 3
    if q.shape != (3 * c,):
        raise ValueError(f"q must be ({3 * c},) to match W {W.shape}, got shape {q.shape}")
    if mu.shape != (c,):
        raise ValueError(f"mu must be ({c},) to match W {W.shape}, got shape {mu.shape}")
    if mask.shape != (c,):
        raise ValueError(f"mask must be ({c},) to match W {W.shape}, got shape {mask.shape}")
    if gamma0 is not None and gamma0.shape != (c, 3):
        raise ValueError(f"gamma0 must be ({c}, 3), got shape {gamma0.shape}")
    if max_iters is not None and (not isinstance(max_iters, int) or max_iters < 1):
        raise ValueError(f"max_iters must be a positive Python int, got {max_iters!r}")
    return c


def _prepare(W, q, mu, mask):
    """Common dtype; W and q with inactive rows/columns zeroed (and W's tangential rows/cols
    of frictionless contacts); the (3C,) activity mask as 0/1."""
    W = jnp.asarray(W)
    dtype = jnp.result_type(W.dtype, jnp.asarray(q).dtype)
    if not jnp.issubdtype(dtype, jnp.floating):
        dtype = jnp.float64 if jax.config.jax_enable_x64 else jnp.float32
    W = W.astype(dtype)
    q = jnp.asarray(q, dtype)
    mu = jnp.maximum(jnp.asarray(mu, dtype), 0.0)
    mask = jnp.asarray(mask, bool)
    m3 = jnp.repeat(mask, 3).astype(dtype)
    # Frictionless contacts have no tangential freedom: leaving their tangential rows out of W
    # changes neither the solution nor the natural map's numerator, and keeps L (hence the
    # step) that of the operator the cones actually let act.
    free = jnp.stack([mask, mask & (mu > 0), mask & (mu > 0)], axis=-1).reshape(-1)
    f3 = free.astype(dtype)
    Wm = W * f3[:, None] * f3[None, :]
    return Wm, q * m3, mu, mask, m3


def _norm_estimate(Wm):
    """An estimate ``L`` of ‖W‖₂ meant to lie above it, from power iteration (usually a few %
    above; it can fall ~5 % short, see ``_POWER_ITERS``).

    At most ``_POWER_ITERS`` iterations from a fixed generic start vector (a deterministic random
    vector, so that no symmetry of the problem, such as the squeeze's left/right antisymmetry,
    can make it orthogonal to the top eigenvector), stopped once the iterate is an eigenvector to
    ``_POWER_TOL`` (see there), times ``_POWER_SAFETY``, capped by ``trace(W)`` (a guaranteed
    upper bound for W ⪰ 0, exact when W has rank one). Returns 1 for ``W = 0`` so that the step
    is finite; then the gradient is 0 anyway.
    """
    n = Wm.shape[0]
    tiny = jnp.finfo(Wm.dtype).tiny
    # A constant of the compiled program: traced, the generator's loop ran in every solve.
    with jax.ensure_compile_time_eval():
        v0 = jax.random.normal(jax.random.PRNGKey(0), (n,), dtype=Wm.dtype)

    def iterate(v):
        w = Wm @ v
        rho = jnp.sum(v * w)  # Rayleigh quotient of the unit v
        settled = safe_norm(w - rho * v) <= _POWER_TOL * rho
        return w / jnp.maximum(safe_norm(w), tiny), settled

    def body(c, _):
        # A cond, not a while loop: reverse-differentiable (contact.gradient = "unrolled").
        return jax.lax.cond(c[1], lambda c: c, lambda c: iterate(c[0]), c), None

    (v, _), _ = jax.lax.scan(body, (v0 / safe_norm(v0), jnp.asarray(False)), None, length=_POWER_ITERS)
    lam = safe_norm(Wm @ v)  # ‖Wv‖ ≥ vᵀWv for unit v: the sharper of the two lower bounds
    lam = jnp.minimum(_POWER_SAFETY * lam, jnp.trace(Wm))
    return jnp.where(lam > 0, lam, 1.0)


def _natural_residual(g, u, mu, m3, L, qmax):
    """Normalised natural-map residual, see ``kkt_residual``. ``g``, ``u``, ``m3`` are (3C,)."""
    c = mu.shape[0]
    r = g - project_cone((g - u / L).reshape(c, 3), mu).reshape(-1)
    r = r * m3
    tiny = jnp.finfo(g.dtype).tiny
    return jnp.max(jnp.abs(r)) / (qmax / L + jnp.max(jnp.abs(g)) + tiny)


def _frozen_scan(step, init, done, trace, max_iters):
    """Apply ``step`` to ``init`` ``max_iters`` times, leaving the carry unchanged once ``done``.

    A bounded ``lax.scan`` (reverse-differentiable, unlike ``while_loop``). The freeze is a
    ``lax.cond``, so a converged single solve skips the work; iterations are grouped in blocks
    of ``_BLOCK`` so that, once converged, whole blocks are skipped at the price of one cond.
    The last block's steps past ``max_iters`` are frozen too, so that the program holds one
    copy of ``step`` (a scan of the remaining single steps would be a second). Under ``vmap``
    conds become selects and every lane runs all the blocks' steps.

    Returns the final carry and ``trace(carry)`` after every iteration, (max_iters,).
    """

    def one(s, k):
        out = jax.lax.cond(done(s) | (k >= max_iters), lambda s: s, step, s)
        return out, trace(out)

    def block(s, b):
        def skip(s):
            return s, jnp.broadcast_to(trace(s), (_BLOCK,))

        ks = b * _BLOCK + jnp.arange(_BLOCK)
        return jax.lax.cond(done(s), skip, lambda s: jax.lax.scan(one, s, ks), s)

    n_blocks = -(-max_iters // _BLOCK)
    s, tr = jax.lax.scan(block, init, jnp.arange(n_blocks))
    return s, tr.reshape(-1)[:max_iters]


def _while(step, init, done, max_iters):
    """``_frozen_scan`` without the trace, as a ``lax.while_loop``: the same iterates and the
    same final carry (it stops where the scan freezes), at a fraction of the cost per iteration
    (no ``lax.cond`` and no carry copies), but not reverse-differentiable. For solves whose
    derivatives are taken implicitly (``jsnap._core.contact.implicit``).

    Each trip of the loop makes ``_UNROLL`` steps, the later ones frozen (a select) once
    ``done`` or past ``max_iters``: at these sizes a step costs its ~30 kernel launches, and the
    loop's own per-trip work is a good part of that. The loop is the solver's only copy of
    ``step`` (a second loop of single steps for the last ``max_iters % _UNROLL`` iterations
    would be a third copy: measured on a 16-contact APGD solve, 0.97 s to compile against 0.62
    s with one copy and ~0.75 s with these two).
    """

    def freeze(k, s):
        stop = done(s) | (k >= max_iters)
        return jax.tree_util.tree_map(lambda a, b: jnp.where(stop, a, b), s, step(s))

    def trips(c):
        return (c[0] < max_iters) & ~done(c[1])

    def unrolled(c):
        s = step(c[1])
        for j in range(1, _UNROLL):
            s = freeze(c[0] + j, s)
        return c[0] + _UNROLL, s

    return jax.lax.while_loop(trips, unrolled, (jnp.asarray(0, jnp.int32), init))[1]


def _mask_gamma(gamma, m3):
    return jnp.where(m3 > 0, gamma, 0.0)


def _initial(gamma0, c, mu, m3, dtype):
    if gamma0 is None:
        return jnp.zeros(3 * c, dtype)
    g = project_cone(jnp.asarray(gamma0, dtype), mu).reshape(-1)
    return _mask_gamma(g, m3)


# ----------------------------------------------------------------------------------------------
# Residuals


def kkt_residual(W, q, mu, mask, gamma):
    """Normalised KKT residual of ``gamma`` for the cone complementarity problem.

    It is the natural-map residual, the fixed-point defect of one projected-gradient step of
    step ``1/L``, in the ∞-norm, relative to the force scale:

        r = ‖gamma − proj_F(gamma − (W gamma + q)/L)‖_∞ / (‖q‖_∞ / L + ‖gamma‖_∞ + tiny)

    over active contacts, with ``L`` the power-iteration estimate of ‖W‖₂ on the active block
    (the same ``L`` that sets APGD's step). It is 0 exactly at a KKT point (and only there: the
    natural map vanishes iff ``-u ∈ N_F(gamma)``), dimensionless, invariant to scaling W or q by
    positive factors (the solution scales by ``b/a`` when ``W → aW``, ``q → bq``), and ≈ the
    relative size of the correction a gradient step would still make.

    What it does not bound: since the step is ``1/L``, a force error along an eigenvector of W
    with a small eigenvalue ``λ`` shows up weighted by ``λ/L``, so forces can be off by up to
    ~cond(W) × r in the soft modes. Measured on the symmetric squeeze (cond 8.5e5): r = 1e-6
    left a 12 % force error, r = 1e-8 0.03 %. On degenerate problems (singular W, redundant
    contacts) the ``‖gamma‖`` in the denominator also lets a solution drifting along null
    directions look converged early. Choose ``tol`` for the conditioning at hand.

    Args:
        W: (3C, 3C) Delassus matrix, symmetric positive semi-definite, mm/(s·N).
        q: (3C,) free relative velocity plus stabilisation, mm/s.
        mu: (C,) friction coefficients ≥ 0.
        mask: (C,) bool, active slots.
        gamma: (C, 3) contact forces, N.

    Returns:
        Scalar residual (dimensionless), dtype of ``W``/``q``.
    """
    _check_shapes(jnp.asarray(W), jnp.asarray(q), jnp.asarray(mu), jnp.asarray(mask))
    Wm, qm, mu, mask, m3 = _prepare(W, q, mu, mask)
    g = _mask_gamma(jnp.asarray(gamma, Wm.dtype).reshape(-1), m3)
    L = _norm_estimate(Wm)
    return _natural_residual(g, Wm @ g + qm, mu, m3, L, jnp.max(jnp.abs(qm)))


def kkt_terms(W, q, mu, mask, gamma):
    """The three KKT violations of ``gamma`` separately, normalised (see ``KKTTerms``).

    Arguments as for ``kkt_residual``. Inactive slots are ignored (their ``gamma`` is taken as
    0 and their velocity is unconstrained).

    Returns:
        ``KKTTerms(primal, dual, complementarity)``, dimensionless scalars.
    """
    _check_shapes(jnp.asarray(W), jnp.asarray(q), jnp.asarray(mu), jnp.asarray(mask))
    Wm, qm, mu, mask, m3 = _prepare(W, q, mu, mask)
    c = mu.shape[0]
    g = _mask_gamma(jnp.asarray(gamma, Wm.dtype).reshape(-1), m3)
    u = (Wm @ g + qm).reshape(c, 3)
    g = g.reshape(c, 3)
    L = _norm_estimate(Wm)
    tiny = jnp.finfo(Wm.dtype).tiny
    s_f = jnp.max(jnp.abs(g)) + jnp.max(jnp.abs(qm)) / L + tiny
    s_v = L * s_f
    act = mask.astype(Wm.dtype)
    primal = safe_norm(g - project_cone(g, mu), axis=-1) * act
    dual = safe_norm(project_cone(-u, mu), axis=-1) * act
    comp = jnp.abs(jnp.sum(g * u, axis=-1)) * act
    return KKTTerms(
        primal=jnp.max(primal) / s_f,
        dual=jnp.max(dual) / s_v,
        complementarity=jnp.max(comp) / (s_f * s_v),
    )


# ----------------------------------------------------------------------------------------------
# Pieces the iterative solvers share


def _setup(W, q, mu, mask, max_iters, tol, gamma0):
    """What every solver starts with: the shapes checked, ``_prepare``'s masked problem, ``tol``
    in its dtype, ``L`` (``_norm_estimate``) and ``‖q‖∞``. Returns
    ``(C, Wm, qm, mu, mask, m3, tol, L, qmax)``."""
    W, q, mu, mask = (jnp.asarray(a) for a in (W, q, mu, mask))
    c = _check_shapes(W, q, mu, mask, max_iters, None if gamma0 is None else jnp.asarray(gamma0))
    Wm, qm, mu, mask, m3 = _prepare(W, q, mu, mask)
    return c, Wm, qm, mu, mask, m3, jnp.asarray(tol, Wm.dtype), _norm_estimate(Wm), jnp.max(jnp.abs(qm))


class _Ops(NamedTuple):
    """Component-major pieces shared by APGD and ADMM (see ``solve_apgd`` for why the iterations
    run on (3, C) arrays: normals, t1, t2 as rows)."""

    cm: object  # contact-major (3C,) -> component-major (3, C)
    to_cm: object  # a (3C, 3C) matrix in contact-major order -> component-major order
    mv: object  # (M, (3, C)) -> (3, C)
    proj: object  # onto the cones, inactive slots zeroed
    residual: object  # (g, W g) -> kkt_residual of g
    qc: jax.Array
    mc: jax.Array


def _ops(c, mu, m3, qm, L, qmax, dtype) -> _Ops:
    def cm(v):
        return v.reshape(c, 3).T

    def to_cm(M):
        return M.reshape(c, 3, c, 3).transpose(1, 0, 3, 2).reshape(3 * c, 3 * c)

    qc, mc = cm(qm), cm(m3)

    def mv(M, v):
        return (M @ v.reshape(-1)).reshape(3, c)

    def proj(v):
        return jnp.stack(_project_cone_split(v[0], v[1], v[2], mu)) * mc

    def residual(g, Wg):
        r = (g - proj(g - (Wg + qc) / L)) * mc
        tiny = jnp.finfo(dtype).tiny
        return jnp.max(jnp.abs(r)) / (qmax / L + jnp.max(jnp.abs(g)) + tiny)

    return _Ops(cm, to_cm, mv, proj, residual, qc, mc)


def _gradient_start(c, Wm, qm, mu, m3, L, qmax, gamma0):
    """What the gradient solvers (APGD, SPG) start from: ``_ops``, the matvec ``v -> W v`` on
    component-major (3, C) arrays, the warm start ``x0`` (projected, masked), ``W x0`` and its
    residual. Returns ``(ops, matvec, x0, Wx0, r0)``.

    The iteration runs on component-major (3, C) arrays (normals, t1, t2 as rows): the cone
    projection is then elementwise on three rows, which XLA fuses into a few kernels per
    iteration (on the CPU a step of this size costs what its kernel launches cost), and the
    reductions run over two short axes, which XLA:CPU does in one kernel, where a (3C,) vector
    longer than 32 is reduced in two. Same iterates as the contact-major form up to round-off.
    """
    o = _ops(c, mu, m3, qm, L, qmax, Wm.dtype)
    Wc = o.to_cm(Wm)

    def matvec(v):
        return o.mv(Wc, v)

    x0 = o.cm(_initial(gamma0, c, mu, m3, Wm.dtype))
    Wx0 = matvec(x0)
    return o, matvec, x0, Wx0, o.residual(x0, Wx0)


def _best_so_far(s, x, r, tol) -> dict:
    """The carry fields ``best``, ``best_r``, ``it`` and ``done`` after an iteration that reached
    ``x`` with residual ``r`` (the solvers return the best iterate, not the last)."""
    better = r < s.best_r
    return dict(
        best=jnp.where(better, x, s.best),
        best_r=jnp.where(better, r, s.best_r),
        it=s.it + 1,
        done=jnp.minimum(r, s.best_r) <= tol,
    )


def _finish(step, init, tol, max_iters, differentiable, return_trace):
    """Run ``step`` from ``init`` (a carry with ``best``, ``best_r``, ``it``, ``done``) as a frozen
    scan or a while loop, and package the best iterate."""
    if differentiable or return_trace:
        final, trace = _frozen_scan(step, init, lambda s: s.done, lambda s: s.best_r, max_iters=max_iters)
    else:
        final = _while(step, init, lambda s: s.done, max_iters)
    sol = ContactSolution(
        gamma=final.best.T,
        iterations=final.it,
        residual=final.best_r,
        converged=final.best_r <= tol,
    )
    return (sol, trace) if return_trace else sol


# ----------------------------------------------------------------------------------------------
# APGD


class _APGDCarry(NamedTuple):
    x: jax.Array  # current iterate gamma_k, (3, C) component-major
    Wx: jax.Array  # W x, kept so that each iteration needs one matvec only
    y: jax.Array  # extrapolated point
    Wy: jax.Array
    theta: jax.Array
    best: jax.Array  # iterate with the smallest residual so far (APGD is not monotone)
    best_r: jax.Array
    it: jax.Array
    done: jax.Array


def solve_apgd(W, q, mu, mask, *, max_iters, tol, gamma0=None, return_trace=False, differentiable=True):
    """Solve the contact problem by accelerated projected gradient with adaptive restart.

    Nesterov/FISTA on ``½γᵀWγ + γᵀq`` over the product of friction cones, fixed step ``1/L``
    (``L`` ≥ ‖W‖₂ from power iteration, see ``kkt_residual``), with O'Donoghue & Candès's
    gradient restart in its composite form: momentum is reset whenever
    ``(y_k − γ_{k+1}) · (γ_{k+1} − γ_k) > 0``, i.e. when the step taken goes uphill. The
    iterate with the smallest residual is returned (accelerated methods are not monotone).

    ``converged`` means ``kkt_residual ≤ tol`` for the returned ``gamma``. In float64 the
    residual goes down to ~1e-13. In float32 it stalls around 1e-8 on random problems, or
    reads exactly 0 once ``(Wγ + q)/L`` drops below the rounding of ``γ``, so it cannot certify
    velocities better than ~eps₃₂ · L ‖γ‖.

    The loop is a ``lax.scan`` of ``max_iters`` steps whose carry freezes once converged (a
    ``lax.cond``), so the function is jit/vmap-able and reverse-differentiable (reverse mode
    stores the carries). A single solve stops working once converged (up to skipping blocks of
    16 frozen iterations); under ``vmap`` the cond becomes a select and every problem pays for
    ``max_iters`` iterations.

    Args:
        W: (3C, 3C) Delassus matrix, symmetric PSD, mm/(s·N). Inactive rows/cols are ignored.
        q: (3C,) free relative velocity plus stabilisation, mm/s.
        mu: (C,) friction coefficients ≥ 0.
        mask: (C,) bool, active slots; inactive slots get exactly 0.
        max_iters: static int, iteration cap.
        tol: residual tolerance (dimensionless).
        gamma0: optional (C, 3) warm start, N (projected onto the cones and masked first).
        return_trace: static bool; if True also return the (max_iters,) residual after each
            iteration (constant once frozen).

    Returns:
        ``ContactSolution`` (and the trace if asked).
    """
    c, Wm, qm, mu, mask, m3, tol, L, qmax = _setup(W, q, mu, mask, max_iters, tol, gamma0)
    dtype = Wm.dtype
    o, matvec, x0, Wx0, r0 = _gradient_start(c, Wm, qm, mu, m3, L, qmax, gamma0)
    proj, residual, qc = o.proj, o.residual, o.qc
    init = _APGDCarry(
        x=x0,
        Wx=Wx0,
        y=x0,
        Wy=Wx0,
        theta=jnp.asarray(1.0, dtype),
        best=x0,
        best_r=r0,
        it=jnp.asarray(0, jnp.int32),
        done=r0 <= tol,
    )

    def step(s):
        x_new = proj(s.y - (s.Wy + qc) / L)
        Wx_new = matvec(x_new)
        r_new = residual(x_new, Wx_new)
        theta_new = 0.5 * s.theta * (jnp.sqrt(s.theta * s.theta + 4.0) - s.theta)
        beta = s.theta * (1.0 - s.theta) / (s.theta * s.theta + theta_new)
        restart = jnp.sum((s.y - x_new) * (x_new - s.x)) > 0
        y_new = jnp.where(restart, x_new, x_new + beta * (x_new - s.x))
        # W y by linearity, exact up to round-off: no second matvec.
        Wy_new = jnp.where(restart, Wx_new, Wx_new + beta * (Wx_new - s.Wx))
        theta_new = jnp.where(restart, jnp.asarray(1.0, dtype), theta_new)
        return _APGDCarry(
            x=x_new, Wx=Wx_new, y=y_new, Wy=Wy_new, theta=theta_new, **_best_so_far(s, x_new, r_new, tol)
        )

    return _finish(step, init, tol, max_iters, differentiable, return_trace)


# ----------------------------------------------------------------------------------------------
# ADMM


# Largest order inverted by Gauss-Jordan sweeps; above it ``_spd_inverse`` splits the matrix in two.
_SWEEP_MAX = 48


def _gauss_jordan_inverse(A):
    """Inverse of an SPD matrix by Gauss–Jordan sweeps (no pivoting: the pivots of an SPD matrix
    are its Schur complements' diagonals, ≥ its smallest eigenvalue): a ``fori_loop`` of one
    rank-1 update per row, in plain XLA operations."""
    n = A.shape[0]
    idx = jnp.arange(n)

    def sweep(k, A):
        row = jax.lax.dynamic_index_in_dim(A, k, 0, keepdims=False)
        d = row[k]
        r = row / d
        B = A - jnp.outer(row, r)
        ek = idx == k
        B = jnp.where(ek[:, None], r[None, :], B)
        B = jnp.where(ek[None, :], r[:, None], B)
        return jnp.where(ek[:, None] & ek[None, :], -1.0 / d, B)

    return -jax.lax.fori_loop(0, n, sweep, A)


def _spd_inverse(A):
    """Inverse of a symmetric positive definite matrix, in plain XLA operations.

    Up to order ``_SWEEP_MAX`` by Gauss–Jordan sweeps in a ``fori_loop``; above it by blocks,
    recursively: with ``A = [[P, Q], [Q', R]]``, ``T = P⁻¹Q`` and the Schur complement
    ``Z = R − Q'T`` (SPD), ``A⁻¹ = [[P⁻¹ + T Z⁻¹ T', −T Z⁻¹], [−Z⁻¹ T', Z⁻¹]]`` in matrix
    products. A sweep is n² elementwise work, cheap as a loop's few fused operations while the
    matrix is small; under ``vmap`` the size switch (``jsnap._core.step._solve``) and the predict-correct
    pass run the whole buffer's problem in every step, and 192 sweeps of the default 64 slots'
    192 x 192 matrix made batched ADMM rollouts 4.4x slower than with the blocks (31 against 137
    scene-steps/s at batch 1; benchmarks/throughput.py --admm). Blocks all the way down to
    unrolled 6 x 6 sweeps ran no faster in a single scene and doubled the rollout's compile time
    (16.9 against 7.6 s, the 1344-dof reduced scene, default contact).
    LAPACK's Cholesky (``jax.scipy.linalg.cho_factor``/``cho_solve``) gave the same ADMM
    iterates, but inside the rollout's ``scan`` its calls cost ~200 µs per step on the 1344-dof
    reduced scene with light contact settings (659 against 449 µs per step, 100 iterations per
    solve; in isolation both take ~15-20 µs for a 36 x 36 matrix).
    """
    n = A.shape[0]
    if n <= _SWEEP_MAX:
        return _gauss_jordan_inverse(A)
    h = n // 2
    P, Q, R = A[:h, :h], A[:h, h:], A[h:, h:]
    Pi = _spd_inverse(P)
    T = Pi @ Q
    Z = R - Q.T @ T
    Zi = _spd_inverse(0.5 * (Z + Z.T))
    U = -T @ Zi
    top = Pi - U @ T.T
    return jnp.block([[0.5 * (top + top.T), U], [U.T, Zi]])


class _ADMMCarry(NamedTuple):
    z: jax.Array  # feasible iterate (on the cones), (3, C) component-major
    u: jax.Array  # scaled multiplier of gamma = z
    best: jax.Array  # iterate with the smallest residual so far (ADMM is not monotone in it)
    best_r: jax.Array
    it: jax.Array
    done: jax.Array


def solve_admm(W, q, mu, mask, *, max_iters, tol, gamma0=None, return_trace=False, differentiable=True):
    """Solve the contact problem by the alternating direction method of multipliers.

    The splitting ``gamma = z`` of ``min ½γᵀWγ + γᵀq + I_F(z)`` (Tasora et al., "Solving
    variational inequalities and cone complementarity problems in nonsmooth dynamics using the
    alternating direction method of multipliers", IJNME 2021), over-relaxed by ``α``
    (``_ADMM_RELAX``), with the penalty ``ρ`` fixed for the solve at ``_ADMM_RHO`` times the mean
    diagonal of W over the free components:

        γ  ← (W + ρI)⁻¹ (ρ (z − u) − q)
        γ̂  ← α γ + (1 − α) z
        z  ← proj_F(γ̂ + u)
        u  ← u + γ̂ − z

    ``(W + ρI)⁻¹`` is formed once per solve (``_spd_inverse``; W is small), so an iteration costs
    two matvecs (the step and ``W z`` for the residual) against APGD's one. The inverse carries the
    curvature that a gradient step lacks: where several contacts slide along one line of a stiff
    hook W is singular and badly conditioned, and APGD needs hundreds of iterations; on the
    recorded solves of the default scene and of the reduced scenes ADMM reaches the same
    residual in 2.8-4.6x fewer iterations on average (docs/contact.md). ``z`` is always on the
    cones; its residual is ``kkt_residual``'s, with APGD's ``L``, so ``tol`` means what it means
    for APGD.
    The warm start sets ``z = proj(gamma0)`` and ``u = −(W z + q)/ρ``, the multiplier that
    makes ``gamma0`` a fixed point when it solves the problem.

    Same loop structure (a frozen scan, or a while loop when ``differentiable=False``),
    arguments and result as ``solve_apgd``.
    """
    c, Wm, qm, mu, mask, m3, tol, L, qmax = _setup(W, q, mu, mask, max_iters, tol, gamma0)
    dtype = Wm.dtype
    # ρ from the mean mobility of the free components (W's diagonal over active contacts' normal
    # and, with friction, tangential rows); L when there is none (then nothing moves anyway).
    diag = jnp.diagonal(Wm)
    n_free = jnp.sum(diag > 0)
    mean_diag = jnp.sum(diag) / jnp.maximum(n_free, 1)
    rho = jnp.where(mean_diag > 0, jnp.asarray(_ADMM_RHO, dtype) * mean_diag, L)
    alpha = jnp.asarray(_ADMM_RELAX, dtype)

    o = _ops(c, mu, m3, qm, L, qmax, dtype)
    # Inactive rows and columns of W are zero, so W + ρI is ρ there: positive definite.
    Ac = o.to_cm(_spd_inverse(Wm + rho * jnp.eye(3 * c, dtype=dtype)))
    Wc = o.to_cm(Wm)
    cm, mv, proj, residual, qc, mc = o.cm, o.mv, o.proj, o.residual, o.qc, o.mc

    z0 = cm(_initial(gamma0, c, mu, m3, dtype))
    Wz0 = mv(Wc, z0)
    r0 = residual(z0, Wz0)
    init = _ADMMCarry(
        z=z0,
        u=-(Wz0 + qc) / rho * mc,
        best=z0,
        best_r=r0,
        it=jnp.asarray(0, jnp.int32),
        done=r0 <= tol,
    )

    def update(z, u):
        g = mv(Ac, rho * (z - u) - qc)
        gh = alpha * g + (1.0 - alpha) * z
        z = proj(gh + u)
        return z, (u + gh - z) * mc

    def step(s):
        z, u = update(s.z, s.u)
        return _ADMMCarry(z=z, u=u, **_best_so_far(s, z, residual(z, mv(Wc, z)), tol))

    return _finish(step, init, tol, max_iters, differentiable, return_trace)


# ----------------------------------------------------------------------------------------------
# SPG


class _SPGCarry(NamedTuple):
    x: jax.Array  # current iterate (on the cones), (3, C) component-major
    Wx: jax.Array
    f: jax.Array  # objective ½ xᵀWx + qᵀx, kept by its exact quadratic update
    alpha: jax.Array  # spectral step for the next iteration
    hist: jax.Array  # (_SPG_MEMORY,) recent objective values (the non-monotone reference)
    best: jax.Array
    best_r: jax.Array
    it: jax.Array
    done: jax.Array


def solve_spg(W, q, mu, mask, *, max_iters, tol, gamma0=None, return_trace=False, differentiable=True):
    """Solve the contact problem by spectral projected gradient (Birgin, Martínez & Raydan,
    SIAM J. Optim. 2000, "SPG2"): a projected-gradient direction with the Barzilai–Borwein step,
    made globally convergent by a non-monotone line search (Grippo–Lampariello–Lucidi: sufficient
    decrease against the largest of the last ``_SPG_MEMORY`` objective values).

    One iteration, from ``γ`` on the cones with gradient ``g = Wγ + q``:

        d  = proj_F(γ − α g) − γ                      (a feasible descent direction)
        λ  = 1 if f(γ + d) ≤ max(recent f) + 1e-4 gᵀd, else the exact line minimum
             min(1, −gᵀd / dᵀWd)                      (f is quadratic: no search loop)
        γ ← γ + λ d                                   (on the cones: a convex combination)
        α ← dᵀd / dᵀWd                                (BB1, the inverse Rayleigh quotient of d)

    One matvec per iteration (``W d``; ``Wγ`` and ``f`` follow by linearity), as APGD. The BB step
    is the inverse of W's curvature along the last step, so it ranges over W's spectrum: long steps
    where the last move was along the soft directions that a fixed step ``1/L`` crawls along (the
    force distribution along a line contact, eigenvalues down to 1e-7 L). On the recorded solves
    of the 1344-dof reduced scene with light contact (float64, from the recorded warm starts, to
    the 1e-6 residual) SPG takes 67 iterations at the median and 120 on average against APGD's
    261 and 260 (docs/contact.md). The residual, ``tol``, the returned iterate (the best by the
    residual) and the loop structure are APGD's; so are the arguments and the result.
    """
    c, Wm, qm, mu, mask, m3, tol, L, qmax = _setup(W, q, mu, mask, max_iters, tol, gamma0)
    o, matvec, x0, Wx0, r0 = _gradient_start(c, Wm, qm, mu, m3, L, qmax, gamma0)
    proj, residual, qc = o.proj, o.residual, o.qc
    f0 = jnp.sum(x0 * (0.5 * Wx0 + qc))
    a_min, a_max = 1.0 / L, _SPG_MAX_STEP / L
    init = _SPGCarry(
        x=x0,
        Wx=Wx0,
        f=f0,
        alpha=a_min,
        hist=jnp.full((_SPG_MEMORY,), f0),
        best=x0,
        best_r=r0,
        it=jnp.asarray(0, jnp.int32),
        done=r0 <= tol,
    )

    def step(s):
        g = s.Wx + qc
        d = proj(s.x - s.alpha * g) - s.x
        Wd = matvec(d)
        gd, dWd, dd = jnp.sum(g * d), jnp.sum(d * Wd), jnp.sum(d * d)
        curved = dWd > 0
        dWd_safe = jnp.where(curved, dWd, 1.0)
        full = s.f + gd + 0.5 * dWd <= jnp.max(s.hist) + _SPG_DECREASE * gd
        lam = jnp.where(full | ~curved, 1.0, jnp.clip(-gd / dWd_safe, 0.0, 1.0))
        x_new = s.x + lam * d
        Wx_new = s.Wx + lam * Wd
        f_new = s.f + lam * gd + 0.5 * lam * lam * dWd
        alpha = jnp.clip(jnp.where(curved, dd / dWd_safe, a_max), a_min, a_max)
        # A select, not a scatter: XLA:CPU compiles the loop into one kernel only without scatters.
        hist = jnp.where(jnp.arange(_SPG_MEMORY) == s.it % _SPG_MEMORY, f_new, s.hist)
        r_new = residual(x_new, Wx_new)
        return _SPGCarry(
            x=x_new, Wx=Wx_new, f=f_new, alpha=alpha, hist=hist, **_best_so_far(s, x_new, r_new, tol)
        )

    return _finish(step, init, tol, max_iters, differentiable, return_trace)


# ----------------------------------------------------------------------------------------------
# PGS


def solve_pgs(W, q, mu, mask, *, max_iters, tol, gamma0=None, return_trace=False, differentiable=True):
    """Solve the contact problem by projected block Gauss–Seidel (the classic baseline).

    One iteration is a sweep over contacts ``i = 0 … C−1`` in order, each using the latest
    values of the others:

        gamma_i ← proj_{F_i}(gamma_i − η_i (W gamma + q)_i),    η_i = 1 / ‖W_ii‖_∞

    where ``W_ii`` is the 3×3 diagonal block and ``‖W_ii‖_∞`` (max absolute row sum) is an
    upper bound of its largest eigenvalue, so each block update is a projected gradient step
    with step ≤ 1/λ_max(W_ii): the objective never increases (block coordinate descent). The
    step is a scalar per block because the projection is Euclidean; a per-component diagonal
    scaling would change the fixed point. On well-separated contacts this converges quickly; on
    strongly coupled ones (the symmetric squeeze) it stalls — the reason APGD is used.

    Same scan/freeze structure, arguments and result as ``solve_apgd``; ``iterations`` counts
    sweeps, and the residual is checked after each sweep.
    """
    c, Wm, qm, mu, mask, m3, tol, L, qmax = _setup(W, q, mu, mask, max_iters, tol, gamma0)
    dtype = Wm.dtype

    idx = jnp.arange(c)
    blocks = Wm.reshape(c, 3, c, 3)[idx, :, idx, :]  # (C, 3, 3) diagonal blocks
    bound = jnp.max(jnp.sum(jnp.abs(blocks), axis=-1), axis=-1)
    # A zero block (an active contact with zero mobility) cannot be moved by its own force.
    eta = jnp.where(bound > 0, 1.0 / jnp.where(bound > 0, bound, 1.0), 0.0)

    def sweep(g):
        def body(i, g):
            rows = jax.lax.dynamic_slice_in_dim(Wm, 3 * i, 3, axis=0)
            ui = rows @ g + jax.lax.dynamic_slice_in_dim(qm, 3 * i, 3)
            gi = jax.lax.dynamic_slice_in_dim(g, 3 * i, 3)
            new = project_cone(gi - eta[i] * ui, mu[i])
            new = jnp.where(mask[i], new, 0.0)
            return jax.lax.dynamic_update_slice_in_dim(g, new, 3 * i, axis=0)

        return jax.lax.fori_loop(0, c, body, g)

    def residual(g):
        return _natural_residual(g, Wm @ g + qm, mu, m3, L, qmax)

    g0 = _initial(gamma0, c, mu, m3, dtype)
    r0 = residual(g0)
    init = (g0, r0, jnp.asarray(0, jnp.int32), r0 <= tol)

    def step(s):
        g_new = sweep(s[0])
        r_new = residual(g_new)
        return (g_new, r_new, s[2] + 1, r_new <= tol)

    if differentiable or return_trace:
        (g, r, it, _), trace = _frozen_scan(step, init, lambda s: s[3], lambda s: s[1], max_iters=max_iters)
    else:
        g, r, it, _ = _while(step, init, lambda s: s[3], max_iters)
    sol = ContactSolution(gamma=g.reshape(c, 3), iterations=it, residual=r, converged=r <= tol)
    return (sol, trace) if return_trace else sol


# ----------------------------------------------------------------------------------------------
# The symmetric squeeze (host-side problem builder for tests and benchmarks)


class SqueezeProblem(NamedTuple):
    """A contact problem plus what it models. Arrays are NumPy float64."""

    W: np.ndarray  # (3C, 3C) mm/(s·N)
    q: np.ndarray  # (3C,) mm/s
    mu: np.ndarray  # (C,)
    mask: np.ndarray  # (C,) bool
    plug_mass: float  # t
    mobility_ratio: float  # plug mobility / hook normal mobility at the tip contact
    condition: float  # cond(W) on the active block


def _cantilever_flexibility(z, EI):
    """Euler–Bernoulli cantilever (clamped at z = 0): deflection at z_a per unit load at z_b."""
    za, zb = np.meshgrid(z, z, indexing="ij")
    lo, hi = np.minimum(za, zb), np.maximum(za, zb)
    return lo**2 * (3 * hi - lo) / (6 * EI)


def symmetric_squeeze_problem(
    n_per_side=4,
    mobility_ratio=1e3,
    mu=0.3,
    *,
    dt=1e-3,
    approach_speed=10.0,
    insertion_speed=10.0,
    capacity=None,
):
    """A rigid light plug squeezed between two symmetric compliant hooks (the paper's case).

    Two identical stiff latches (cantilevers along z, clamped at z = 0, length 5 mm, thickness
    2 mm in x, width 4 mm in y, ABS E = 2200 MPa, ν = 0.35) face each other across the plug.
    The plug's edge touches each hook's lead ramp along a line across the width at the tip
    (z = 5 mm), sampled by ``n_per_side`` points over y; left hook normals are +x, right hook
    normals −x (normals point from hook into the plug), ``t1 = z`` (insertion axis),
    ``t2 = n × t1``.

    Mobility (velocity per force over a PMI step of length ``dt``):

    - Hooks: quasi-static, ``(2/dt) C_h`` with ``C_h`` the hook's flexibility at the contacts
      (beam bending in x and y, torsion for the y-offsets, axial in z, plus a local contact
      compliance). The first bending mode of such a latch is far above 1/dt, so the mass term of
      ``S = 2M/dt + (dt/2)K`` is negligible.
    - Plug: a free rigid body (translation only; its rotation is held by the gripper) of mass
      ``m``, mobility ``dt/(2m)`` in every direction: ``(dt/2m) G Gᵀ``, ``G`` (3C × 3) summing
      the contact forces into the plug's net force.

    ``W = (2/dt) R C_h Rᵀ + (dt/2m) G Gᵀ``. The plug term is a rank-3 matrix with huge
    eigenvalues: any imbalance between the two hooks' forces moves the light plug fast, while
    the balanced (squeezing) forces are resisted only by the stiff hooks. ``mobility_ratio`` =
    ``(dt/2m) / ((2/dt) c_tip)`` = ``dt² / (4 m c_tip)`` sets ``m``: at dt = 1 ms, 10 is a
    2.3 g plug, 100 0.23 g, 1e3 23 mg (``c_tip`` ≈ 1.1e-2 mm/N). Block Gauss–Seidel,
    updating one contact at a time, must then move the plug back and forth between the hooks,
    which is why it stalls.

    ``q``: both hooks move into the plug at ``approach_speed`` (mm/s) while the plug slides
    down (−z) at ``insertion_speed``, plus a penetration-stabilisation term that differs
    slightly between contacts: ``q_n = −approach − 0.2 d_j / dt`` with depths ``d_j`` in
    [0, 10] µm, ``q_t1 = −insertion``, ``q_t2 = 0``.

    Args:
        n_per_side: contact points per hook.
        mobility_ratio: plug mobility over a hook's tip normal mobility (dimensionless).
        mu: friction coefficient.
        dt: time step, s.
        approach_speed: hooks' normal speed into the plug, mm/s.
        insertion_speed: plug's speed along −z, mm/s.
        capacity: number of slots (≥ 2 n_per_side); extra slots are inactive (mask False).

    Returns:
        ``SqueezeProblem`` (NumPy float64).
    """
    k = int(n_per_side)
    c_act = 2 * k
    cap = c_act if capacity is None else int(capacity)
    if cap < c_act:
        raise ValueError(f"capacity {cap} < 2 * n_per_side = {c_act}")
    E, nu, length, h, b = 2200.0, 0.35, 5.0, 2.0, 4.0
    G_mod = E / (2 * (1 + nu))
    Ix, Iy = b * h**3 / 12, h * b**3 / 12
    J_t = b * h**3 * (1 / 3 - 0.21 * (h / b) * (1 - (h / b) ** 4 / 12))  # rectangle torsion
    area = b * h
    c_local = 1e-3  # mm/N, local contact compliance ~ 1/(E a), patch a ~ 0.5 mm

    # The plug's edge touches each hook's lead ramp along a line across the width (z = L):
    # k points spread over y. Points on one line of a stiff arm are strongly coupled (same
    # bending deflection): the hook's own block is nearly rank one plus the local compliance.
    z = np.full(k, length)
    y = np.linspace(-(b / 2 - 0.25), b / 2 - 0.25, k) if k > 1 else np.zeros(1)
    fx = _cantilever_flexibility(z, E * Ix)
    fy = _cantilever_flexibility(z, E * Iy)
    zz = np.minimum.outer(z, z)
    # Torsion: a force in x at offset y twists the arm; x-displacement at y' is y y' z / (G J).
    fx = fx + np.outer(y, y) * zz / (G_mod * J_t)
    fz = zz / (E * area)
    # Global-axis flexibility of one hook, point-major blocks (x, y, z).
    Ch = np.zeros((3 * k, 3 * k))
    Ch[0::3, 0::3], Ch[1::3, 1::3], Ch[2::3, 2::3] = fx, fy, fz
    Ch += c_local * np.eye(3 * k)
    c_tip = Ch[0, 0]  # normal flexibility at a contact

    ex, _, ez = np.eye(3)
    frames = []
    for side in (+1.0, -1.0):
        nrm = side * ex
        frames += [np.stack([nrm, ez, np.cross(nrm, ez)])] * k
    R = np.zeros((3 * c_act, 3 * c_act))
    for i, Ri in enumerate(frames):
        R[3 * i : 3 * i + 3, 3 * i : 3 * i + 3] = Ri
    # Hooks are independent: block-diagonal flexibility in global axes, then into contact frames.
    Ch2 = np.zeros((3 * c_act, 3 * c_act))
    Ch2[: 3 * k, : 3 * k] = Ch2[3 * k :, 3 * k :] = Ch
    W_hook = (2 / dt) * R @ Ch2 @ R.T
    hook_mob = (2 / dt) * c_tip
    plug_mob = mobility_ratio * hook_mob
    plug_mass = dt / (2 * plug_mob)
    G = np.concatenate(frames, axis=0)  # (3C, 3): rows R_i, so Gᵀ γ = Σ R_iᵀ γ_i = net force
    W_act = W_hook + plug_mob * G @ G.T
    W_act = 0.5 * (W_act + W_act.T)

    s = np.linspace(0.0, 1.0, k)
    depth = 0.01 * np.concatenate([s, s])  # mm, the same on both hooks: a symmetric squeeze
    q_act = np.zeros((c_act, 3))
    q_act[:, 0] = -approach_speed - 0.2 * depth / dt
    q_act[:, 1] = -insertion_speed

    W = np.zeros((3 * cap, 3 * cap))
    W[: 3 * c_act, : 3 * c_act] = W_act
    q = np.zeros(3 * cap)
    q[: 3 * c_act] = q_act.reshape(-1)
    mu_arr = np.full(cap, float(mu))
    mask = np.arange(cap) < c_act
    ev = np.linalg.eigvalsh(W_act)
    return SqueezeProblem(
        W=W,
        q=q,
        mu=mu_arr,
        mask=mask,
        plug_mass=float(plug_mass),
        mobility_ratio=float(mobility_ratio),
        condition=float(ev[-1] / ev[0]),
    )
