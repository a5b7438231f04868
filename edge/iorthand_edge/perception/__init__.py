"""Edge perception: camera sources, ArUco detection and pose, chaining to the robot base frame, filtering.

:class:`iorthand_edge.perception.pipeline.PerceptionPipeline` runs in the edge's media process
(:mod:`iorthand_edge.media`), out of the control process; :func:`iorthand_edge.perception.cli.register` adds the
calibration commands to ``iorthand``.
"""
