"""Case files: a whole simulation described in TOML, validated before anything runs.

Three parts: :mod:`demstep.case.schema` (every key with its unit, loading and
validation: the reference of the format), :mod:`demstep.case.build` (a Simulation
from a case, and the checks of the initial state) and :mod:`demstep.case.stages`
(what a stage changes when it starts).
"""

from demstep.case.build import (
    build_law, build_simulation, build_timestep, build_walls, check_initial_state,
    generate_particles,
)
from demstep.case.schema import (
    Case, box_wall_names, case_from_dict, case_from_text, check_case, dump_case, load_case,
)
from demstep.case.stages import apply_stage, check_stages

__all__ = ["Case", "apply_stage", "box_wall_names", "build_law", "build_simulation",
           "build_timestep", "build_walls", "case_from_dict", "case_from_text", "check_case",
           "check_initial_state", "check_stages", "dump_case", "generate_particles",
           "load_case"]
