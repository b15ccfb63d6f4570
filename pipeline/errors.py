"""Exception hierarchy: re-exported from :mod:`skyroute.stages.base` (its one home, at the
bottom of the package layers) for API stability."""

from skyroute.stages.base import (  # noqa: F401
    CacheError,
    ClusterError,
    CRSError,
    DataError,
    DegenerateCostError,
    InputError,
    PlanningError,
    ScenarioError,
    SkyrouteError,
    UnknownNameError,
)

__all__ = ["SkyrouteError", "ScenarioError", "UnknownNameError", "DataError", "InputError", "CRSError", "CacheError", "ClusterError", "PlanningError", "DegenerateCostError"]
