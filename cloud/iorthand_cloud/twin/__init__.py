"""The digital twin: latest state of every robot, snapshots, previews, and a rerun visualisation.

Modules: ``config`` (YAML → dataclasses), ``state`` (pure store of the latest state per robot and the
snapshot), ``model`` (pure geometry of the drawing: arm from DH parameters, camera frustum, scene),
``viz`` (rerun logging in its own thread behind a drop-oldest queue), ``server`` (where the rerun data goes:
web viewer relay, gRPC, file), ``service`` (Zenoh: subscriptions, liveliness, queryables), ``cli``.
"""
