"""Parallel-bond kernel (:mod:`demstep.contact.bonds`): forces and moments of the
intact bonds, their breakage, and the bonds' ledger terms."""

from __future__ import annotations

import math

from demstep._numba import njit
from demstep.contact.bonds import bond_section
from demstep.contact.geometry import into_tangent_plane, pair_geometry


@njit
def bond_forces(x, v, w, r, bonds, periodic_len, box_rate, dt, dim, force, torque, box_sums):
    """Advance every intact bond of ``bonds`` (:class:`demstep.state.Bonds`) by the
    relative motion of its bond point over the last step (``dt`` [T]: the step that
    produced x(t), 0 at the first step), break those whose rim stresses reach the
    strengths, add the forces and moments of the others to ``force``/``torque``
    (serial: bonds share particles). ``box_rate`` (3,): the periodic lengths' rates;
    ``box_sums`` receives the bonds' shares of the virial and of the boundary sum
    (rows 0 and 1, as :func:`demstep.kernels.dem._pair_loop`).
    Returns (strain energy held by the bonds, energy released by the bonds broken in
    this step, bonds broken in this step)."""
    stored = 0.0
    released = 0.0
    broken = 0
    len0, len1, len2 = periodic_len[0], periodic_len[1], periodic_len[2]
    for b in range(bonds.i.shape[0]):
        if bonds.intact[b] == 0:
            continue
        i = bonds.i[b]
        j = bonds.j[b]
        d0, d1, d2, dist, _, a_i, a_j, n0, n1, n2 = pair_geometry(
            x[i, 0], x[i, 1], x[i, 2], x[j, 0], x[j, 1], x[j, 2], r[i], r[j], len0, len1, len2)
        nx, ny, nz = d0 / dist, d1 / dist, d2 / dist
        area, second, polar = bond_section(bonds.radius[b], dim)
        kn = bonds.k_n[b]
        ks = bonds.k_s[b]
        # relative velocity of j's bond point w.r.t. i's (as in the contact law)
        vix = v[i, 0] + a_i * (w[i, 1] * nz - w[i, 2] * ny)
        viy = v[i, 1] + a_i * (w[i, 2] * nx - w[i, 0] * nz)
        viz = v[i, 2] + a_i * (w[i, 0] * ny - w[i, 1] * nx)
        vjx = v[j, 0] - a_j * (w[j, 1] * nz - w[j, 2] * ny) - n0 * box_rate[0]
        vjy = v[j, 1] - a_j * (w[j, 2] * nx - w[j, 0] * nz) - n1 * box_rate[1]
        vjz = v[j, 2] - a_j * (w[j, 0] * ny - w[j, 1] * nx) - n2 * box_rate[2]
        dux, duy, duz = (vjx - vix) * dt, (vjy - viy) * dt, (vjz - viz) * dt
        dun = dux * nx + duy * ny + duz * nz
        dpx, dpy, dpz = (w[j, 0] - w[i, 0]) * dt, (w[j, 1] - w[i, 1]) * dt, (w[j, 2] - w[i, 2]) * dt
        dpn = dpx * nx + dpy * ny + dpz * nz
        # normal force and twisting moment: scalars along n; shear force and bending
        # moment: vectors rotated into the current tangent plane first
        fn = bonds.normal[b] - kn * area * dun
        sx, sy, sz = into_tangent_plane(bonds.shear[b, 0], bonds.shear[b, 1], bonds.shear[b, 2], nx, ny, nz)
        sx -= ks * area * (dux - dun * nx)
        sy -= ks * area * (duy - dun * ny)
        sz -= ks * area * (duz - dun * nz)
        mt = bonds.twist[b] - ks * polar * dpn
        bx, by, bz = into_tangent_plane(bonds.bend[b, 0], bonds.bend[b, 1], bonds.bend[b, 2], nx, ny, nz)
        bx -= kn * second * (dpx - dpn * nx)
        by -= kn * second * (dpy - dpn * ny)
        bz -= kn * second * (dpz - dpn * nz)
        shear = math.sqrt(sx * sx + sy * sy + sz * sz)
        bend = math.sqrt(bx * bx + by * by + bz * bz)
        rb = bonds.radius[b]
        sigma = -fn / area + bend * rb / second
        tau = shear / area + (abs(mt) * rb / polar if polar > 0.0 else 0.0)
        energy = fn * fn / (2.0 * kn * area) + bend * bend / (2.0 * kn * second)
        if ks > 0.0:
            energy += shear * shear / (2.0 * ks * area)
            if polar > 0.0:
                energy += mt * mt / (2.0 * ks * polar)
        if sigma >= bonds.sigma_c[b] or tau >= bonds.tau_c[b]:
            bonds.intact[b] = 0
            released += energy
            broken += 1
            bonds.normal[b] = 0.0
            bonds.twist[b] = 0.0
            bonds.energy[b] = 0.0
            for k in range(3):
                bonds.shear[b, k] = 0.0
                bonds.bend[b, k] = 0.0
            continue
        bonds.normal[b] = fn
        bonds.twist[b] = mt
        bonds.shear[b, 0], bonds.shear[b, 1], bonds.shear[b, 2] = sx, sy, sz
        bonds.bend[b, 0], bonds.bend[b, 1], bonds.bend[b, 2] = bx, by, bz
        bonds.energy[b] = energy
        fx, fy, fz = fn * nx + sx, fn * ny + sy, fn * nz + sz
        mx, my, mz = mt * nx + bx, mt * ny + by, mt * nz + bz
        stored += energy
        box_sums[0, 0] += fx * d0
        box_sums[0, 1] += fy * d1
        box_sums[0, 2] += fz * d2
        box_sums[1, 0] += fx * n0
        box_sums[1, 1] += fy * n1
        box_sums[1, 2] += fz * n2
        force[j, 0] += fx
        force[j, 1] += fy
        force[j, 2] += fz
        force[i, 0] -= fx
        force[i, 1] -= fy
        force[i, 2] -= fz
        cx, cy, cz = ny * fz - nz * fy, nz * fx - nx * fz, nx * fy - ny * fx
        torque[i, 0] += -a_i * cx - mx
        torque[i, 1] += -a_i * cy - my
        torque[i, 2] += -a_i * cz - mz
        torque[j, 0] += -a_j * cx + mx
        torque[j, 1] += -a_j * cy + my
        torque[j, 2] += -a_j * cz + mz
    return stored, released, broken
