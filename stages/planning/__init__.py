"""skyroute.stages.planning: the strategic planner of seed 000 (section III).

* :mod:`.problem`  -- :class:`PlanningProblem`: validity (floor/ceiling/angle/wind) and the
  four costs of eq. 11 on one GNSS coverage level D_j (compiled kernels);
* :mod:`.grid_planner` -- deterministic A* on a 3-D lattice (STEP I alternative);
* :mod:`.bitstar` -- OMPL BIT* with the eq. 11 objective (STEP I, seed 000 III-A);
* :mod:`.step1` -- STEP I driver: planner choice, energy re-plan loop, all D_j levels;
* :mod:`.fixedwing` -- the fixed-wing planners of seed 002 (``eeastar``, ``astar-fw``,
  ``energy-optimal``) on a heading-aware lattice (kernels in :mod:`.fw_kernels`; which planner
  fits which vehicle kind: :mod:`.kinds`).
"""
