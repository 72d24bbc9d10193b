"""The turn factor of the 'auto' step's drift certificate (a kernel of its own, shared
by :mod:`demstep.timestep.certificate` and the mesh kernels, :mod:`demstep.kernels.meshes`,
which measure the mesh contacts' drift at every step)."""

from __future__ import annotations

import math

from demstep._numba import njit

#: relative margin added to the root :func:`turn_factor` finds (its Newton iterates
#: approach the root from above in exact arithmetic; this covers their rounding), and
#: the most iterations it takes (an early stop leaves a larger, still valid, bound)
TURN_FACTOR_MARGIN = 1e-12
TURN_FACTOR_ITERATIONS = 30


@njit(inline="always")
def turn_factor(trans, rot, b_n, b_t, planar):
    """lambda_max(M) of :mod:`demstep.timestep.certificate`'s doc, an upper bound on
    |E(n') - E(n)| / |n' - n| for a turn at the arms now: ``trans`` = tau^2 = 1/m_i + 1/m_j, ``rot`` = rho^2, the
    normal and tangential coefficients ``b_n``, ``b_t`` (springs or dashpots); for
    disks (``planar``) the 2 x 2 block's, in closed form. In 3D the largest root of
    det(M - x) = -(x^3 - A x^2 - (B^2 + C^2) x + A C^2), which is convex and increasing
    from A (<= the root) on: Newton's iterates from the upper bound b_t rho l + A
    decrease to it and stay above it, until a step is below 1e-14 of it, plus
    :data:`TURN_FACTOR_MARGIN`."""
    big_a = abs(b_n - b_t) * trans
    b2 = b_t * b_t * trans * rot
    if planar:
        return (0.5 * big_a + math.sqrt(0.25 * big_a * big_a + b2)) * (1.0 + TURN_FACTOR_MARGIN)
    c2 = b_t * b_t * rot * rot
    x = b_t * math.sqrt(rot * (trans + rot)) + big_a
    for _ in range(TURN_FACTOR_ITERATIONS):
        slope = x * (3.0 * x - 2.0 * big_a) - (b2 + c2)
        value = x * (x * (x - big_a) - (b2 + c2)) + big_a * c2
        if slope <= 0.0 or value <= 0.0:
            break
        step = value / slope
        x -= step
        if step <= 1e-14 * x:
            break
    return x * (1.0 + TURN_FACTOR_MARGIN)
