"""Particles entering and leaving a run: inserters (a rate, a region or an inlet face,
a radius distribution) and outlets (:mod:`demstep.feed.feed`), their regions
(:mod:`demstep.feed.regions`) and radius distributions
(:mod:`demstep.feed.distributions`). See ``docs/insertion.md``."""

from demstep.feed.distributions import RadiusDistribution, distribution_from_spec
from demstep.feed.feed import Feed, Inserter, Outlet
from demstep.feed.regions import (BoxRegion, CylinderRegion, FaceRegion, Region, SphereRegion,
                                  region_from_spec)

__all__ = ["BoxRegion", "CylinderRegion", "FaceRegion", "Feed", "Inserter", "Outlet",
           "RadiusDistribution", "Region", "SphereRegion", "distribution_from_spec",
           "region_from_spec"]
