"""The embedded benchmark: procedural two-view indoor scenes (renderer + TFDS builder)."""
