"""Path planning for a multicopter at a commanded altitude, on the semantic costmap.

Pure computation (no I/O, never imports ``companion``):

* :mod:`planner.cspace` - the altitude rule and the precomputed clearance/free/cost fields;
* :mod:`planner.gridsearch` - grid Dijkstra (first paths, disconnection proofs, goal snapping)
  and any-angle post-processing;
* :mod:`planner.ompl_backend` - OMPL planners with the length + map-cost objective;
* :mod:`planner.planner` - :class:`~planner.planner.Planner`, which ties them together;
* :mod:`planner.trajectory` - time parametrisation under speed/acceleration/yaw-rate limits;
* :mod:`planner.worker` - the same planner in a separate process (OMPL holds the GIL);
* :mod:`planner.types` - :class:`~planner.types.PlanResult` and :class:`~planner.types.PlanStatus`.
"""
