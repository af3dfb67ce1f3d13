"""The embedded benchmark: procedural two-view indoor scenes (sampling, ray casting, builder)."""
