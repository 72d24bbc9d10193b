"""Hot loops of the time-step analysis."""

import numpy as np

from demstep._numba import njit


@njit
def _stiffness_diagonal(i, j, normal, arm_i, arm_j, k_n, k_s, n, nd, rotation):
    dim = normal.shape[1]
    diag = np.zeros((n, nd))
    for c in range(i.shape[0]):
        for side in range(2):
            p = i[c] if side == 0 else j[c]
            if p < 0:
                continue
            arm = arm_i[c] if side == 0 else arm_j[c]
            rot = k_s[c] * arm * arm
            for k in range(dim):
                n2 = normal[c, k] * normal[c, k]
                diag[p, k] += k_n[c] * n2 + k_s[c] * (1.0 - n2)
                if rotation and dim == 3:
                    diag[p, dim + k] += rot * (1.0 - n2)
            if rotation and dim == 2:
                diag[p, 2] += rot
    return diag


def stiffness_diagonal_kernel(contacts, n_particles: int, nd: int, rotation: bool) -> np.ndarray:
    """Summed contact stiffness per particle DOF (n, nd); see timestep.assembly."""
    return _stiffness_diagonal(contacts.i, contacts.j, contacts.normal, contacts.arm_i,
                               contacts.arm_j, contacts.k_n, contacts.k_s, int(n_particles),
                               int(nd), bool(rotation))
