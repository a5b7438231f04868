"""The recorder: Zenoh traffic → MCAP sessions, crash repair, annotations, replay, reports and rerun export.

Modules: ``config`` (dataclasses), ``service`` (the Zenoh service and its writer thread), ``segments`` (MCAP
files split by size and duration), ``manifest`` (the session's description and per-key statistics),
``repair`` (segments left without a footer), ``reader`` (a session's messages in time order), ``replay``,
``metrics`` (pure maths of the session report), ``report`` (its I/O and plots), ``export`` (.rrd), ``client``
(query helpers), ``simulate`` (a synthetic full-rate publisher for tests and benchmarks), ``cli``.
Beside its raw segments each session holds ``foxglove/``: the same session in Foxglove's schemas
(:mod:`iorthand_cloud.foxglove_channels`), which no reader of the raw segments opens.
"""
