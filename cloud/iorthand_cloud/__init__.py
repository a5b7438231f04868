"""iorthand cloud services: digital twin, recorder, replay, reports."""
