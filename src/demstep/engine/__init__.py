"""The DEM engine: a :class:`Simulation` and the parts it is made of.

``simulation.py`` holds the Simulation (the state bundles, the order of a step, the run
loop, triggers and outputs); the parts that act between chunks of steps each own their
state: ``lists.py`` (neighbour lists), ``auto_step.py`` (the certified 'auto' time
step), ``ordering.py`` (the particles' order in memory), ``boundaries.py`` (walls and
the periodic box), ``bonding.py`` (parallel bonds); ``analysis.py`` hands the state to
the time-step analysis, ``restore.py`` checks a checkpoint before it is restored, and
``settings.py`` holds the TimeStep and Damping settings.
"""

from demstep.engine.settings import Damping, TimeStep
from demstep.engine.simulation import STATE_NAMES, Simulation

__all__ = ["Damping", "STATE_NAMES", "Simulation", "TimeStep"]
