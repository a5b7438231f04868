"""The operator console. ``settings``, ``model`` and ``controller`` import no UI; ``app`` is the textual UI."""
