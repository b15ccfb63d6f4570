"""skyroute.stages: one module per physical concern (surface, almanac, occlusion, DOP, ...)."""
