"""What inserted particles are made of and where they go: regions
(:mod:`demstep.feed.regions`) and radius distributions
(:mod:`demstep.feed.distributions`). The inserters and outlets that use them act on a
Simulation: :mod:`demstep.engine.feed`. See ``docs/insertion.md``."""

from demstep.feed.distributions import RadiusDistribution, distribution_from_spec
from demstep.feed.regions import (BoxRegion, CylinderRegion, FaceRegion, Region, SphereRegion,
                                  region_from_spec)

__all__ = ["BoxRegion", "CylinderRegion", "FaceRegion", "RadiusDistribution", "Region", "SphereRegion", "distribution_from_spec",
           "region_from_spec"]
