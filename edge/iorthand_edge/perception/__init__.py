"""Edge perception: camera sources, ArUco detection and pose, chaining to the robot base frame, filtering.

The lead wires :class:`iorthand_edge.perception.pipeline.PerceptionPipeline` into the edge agent and
:func:`iorthand_edge.perception.cli.register` into the ``iorthand`` command.
"""
