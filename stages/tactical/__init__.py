"""skyroute.stages.tactical: the tactical phase of seed 001 (section 3.2).

During the flight the remaining plan is checked against unfavourable events (new intruders,
track updates, wind, GNSS outages, temporary no-fly zones, new obstacles); when one
compromises it, three replanning levels run and the cheapest valid solution replaces the rest
of the plan, or the vehicle lands at the nearest reachable landing site.

* :mod:`.log`      -- the flight record (:class:`~.log.FlightLog`) every output is written from;
* :mod:`.conflict` -- exact separation checks of a timed trajectory against intruder tracks
  (:class:`~.conflict.IntruderTracks`, :func:`~.conflict.first_conflict`,
  :func:`~.conflict.min_separation`) and the state-based N-aircraft detector
  (:func:`~.conflict.pairwise_conflicts`, BlueSky's numpy baseline
  :func:`~.conflict.pairwise_conflicts_numpy`);
* :mod:`.outputs`  -- tactical.csv, flown.geojson / .csv, intruders.geojson and the figures;
* :mod:`.zones`, :mod:`.octant`, :mod:`.octant_replan`, :mod:`.zone_field` -- seed 004's octant
  method: dense traffic zones, octant avoidance, and the dense zones as obstacles of the
  incrementally updated potential field whose gradient motion re-routes the plan.
"""
