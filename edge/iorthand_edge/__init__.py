"""iorthand edge agent: the safety authority on the end-effector computer."""
