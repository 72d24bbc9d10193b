"""Critical time step of central-difference DEM (O'Sullivan & Bray 2004 and beyond).

Methods (names used throughout, in the CLI and in JSON):

``exact``           lambda_max of M^-1/2 K M^-1/2 for the assembly's sparse K (coupled
                    contact formulation, walls and fixed particles included).
``exact-periodic``  the infinite periodic lattice by Bloch-wave analysis.
``element-coupled`` Rayleigh bound from coupled contact elements (rigorous).
``element-paper``   the paper's contact elements (eqs. 6-19) and Rayleigh's bound.
``nodal``           per-body summed stiffness (YADE GlobalStiffnessTimeStepper rule).
``itasca``          sqrt(m_min / K_max) (Itasca 1998).
``guidance``        the paper's 0.3 (2D) / 0.17 (3D) sqrt(m_min / K_max).

The module depends on particles and contacts only, never on the engine.
"""

from demstep.timestep.stability import (  # noqa: F401
    alpha_of, dt_from_lambda, lambda_from_dt, rayleigh_damped_dt,
)
from demstep.timestep.estimates import (  # noqa: F401
    METHODS, Estimate, TimeStepReport, estimate_time_steps,
)
