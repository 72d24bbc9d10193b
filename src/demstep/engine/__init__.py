"""The DEM engine: a :class:`Simulation` and the parts it is made of.

``simulation.py`` holds the Simulation (the state bundles, the order of a step, the run
loop, triggers and outputs); the parts that act between chunks of steps each own their
state: ``lists.py`` (neighbour lists), ``auto_step.py`` (the certified 'auto' time
step), ``ordering.py`` (the particles' order in memory), ``boundaries.py`` (walls and
the periodic box), ``bonding.py`` (parallel bonds); ``analysis.py`` hands the state to
the time-step analysis, ``restore.py`` checks a checkpoint before it is restored, and
``settings.py`` holds the TimeStep and Damping settings; ``feed.py`` (inserters and
outlets) and ``population.py`` (particles added and removed) let particles come and go.
"""

from demstep.engine.feed import Feed, Inserter, Outlet
from demstep.engine.settings import Damping, TimeStep
from demstep.engine.simulation import STATE_NAMES, Simulation

__all__ = ["Damping", "Feed", "Inserter", "Outlet", "STATE_NAMES", "Simulation", "TimeStep"]
