"""Depth on a robot: `DepthPredictor` (metric scale, recordings), scale recovery,
depth files, and a trained model exported to one file and run with JAX and numpy
only (`export`, `deploy`).
"""
