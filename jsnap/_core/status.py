"""What can go wrong in a step, as bit flags carried in every result (``Result.flags``).

Under ``jit`` and ``vmap`` nothing can be raised, and nothing is silently replaced: each step
reports what happened in an int32 bit mask; :func:`describe` turns a history of masks into a
message naming the first step, and the command line exits non-zero when an error bit is set.
"""

from __future__ import annotations

import enum

import numpy as np

__all__ = [
    "CONTACT_OVERFLOW",
    "DEEP_PENETRATION",
    "ENERGY_CREATED",
    "ERRORS",
    "INVALID_PARAMS",
    "NON_FINITE",
    "NOT_CONVERGED",
    "Flag",
    "describe",
    "first_problem",
]

# Errors: the result is not the physics asked for.
INVALID_PARAMS = 1  # a physical parameter is NaN or out of its range (outputs are NaN)
NON_FINITE = 2  # the step produced a non-finite state or force
ENERGY_CREATED = 4  # the deformable part holds more energy than the rigid part's work put in
CONTACT_OVERFLOW = 8  # more contact candidates than buffer slots: some were dropped
DEEP_PENETRATION = 32  # the deformable part stayed deep inside the rigid part for several steps
# Warnings: the result is what was asked for, less tightly.
NOT_CONVERGED = 16  # the contact solve stopped at its iteration cap above 100x its tolerance

ERRORS = INVALID_PARAMS | NON_FINITE | ENERGY_CREATED | CONTACT_OVERFLOW | DEEP_PENETRATION


class Flag(enum.IntFlag):
    """The bits of ``Result.flags``.

    Errors, the result is not the physics asked for (``ERRORS`` is their union):

    - ``INVALID_PARAMS``: a physical parameter is NaN or out of its range (outputs are NaN);
    - ``NON_FINITE``: the step produced a non-finite state or force;
    - ``ENERGY_CREATED``: the deformable part holds more energy than the rigid part's work put in;
    - ``CONTACT_OVERFLOW``: more contact candidates than buffer slots (some were dropped);
    - ``DEEP_PENETRATION``: a point of the deformable part stayed inside the rigid part deeper
      than the contact resolves for several steps (the contact lost hold of it).

    Warning, the result is what was asked for, less tightly:

    - ``NOT_CONVERGED``: the contact solve stopped at its iteration cap above 100x its tolerance.
    """

    INVALID_PARAMS = INVALID_PARAMS
    NON_FINITE = NON_FINITE
    ENERGY_CREATED = ENERGY_CREATED
    CONTACT_OVERFLOW = CONTACT_OVERFLOW
    DEEP_PENETRATION = DEEP_PENETRATION
    NOT_CONVERGED = NOT_CONVERGED
    ERRORS = ERRORS


_WHAT = {
    INVALID_PARAMS: "invalid parameters (a value of E, nu, rho, alpha, beta or friction is NaN or "
    "out of its range): every output is NaN",
    NON_FINITE: "non-finite state or contact force",
    ENERGY_CREATED: "the deformable part gained more energy than the rigid part's work (the contact "
    "solve failed): results are not physical",
    CONTACT_OVERFLOW: "more contact candidates than contact.capacity slots: points were dropped "
    "(raise contact.capacity)",
    DEEP_PENETRATION: "a point of the deformable part stayed inside the rigid part for several steps, "
    "deeper than the contact resolves (Result.penetration): the contact lost hold of it and the forces "
    "are not physical (contact.stabilisation = 0.1, or a smaller solver.dt, lets the contact push it out)",
    NOT_CONVERGED: "the contact solver stopped at contact.iterations above 100x contact.tolerance",
}


def first_problem(flags, bits: int = ERRORS) -> tuple[int, int] | None:
    """``(step, bit)`` of the first step (0-based) whose flags hold one of ``bits`` (the most
    severe bit of that step), or None. ``flags``: (n,) int (one rollout)."""
    f = np.asarray(flags).reshape(-1) & bits
    hit = np.flatnonzero(f)
    if hit.size == 0:
        return None
    k = int(hit[0])
    bit = next(
        b
        for b in (INVALID_PARAMS, NON_FINITE, ENERGY_CREATED, DEEP_PENETRATION, CONTACT_OVERFLOW, NOT_CONVERGED)
        if f[k] & b
    )
    return k, bit


def describe(flags, bits: int = ERRORS) -> str:
    """``"ok"``, or a message naming the first step with a problem among ``bits`` and how many
    steps had each kind (one rollout's ``(n,)`` flags)."""
    found = first_problem(flags, bits)
    if found is None:
        return "ok"
    k, bit = found
    f = np.asarray(flags).reshape(-1) & bits
    counts = [
        f"{_WHAT[b].split(':')[0].split(' (')[0]}: {int(np.count_nonzero(f & b))} steps"
        for b in _WHAT
        if np.any(f & b)
    ]
    return f"step {k + 1}: {_WHAT[bit]} ({'; '.join(counts)})"
