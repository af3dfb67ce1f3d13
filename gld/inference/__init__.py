"""Depth on a robot: `DepthPredictor` (metric scale, recordings), scale recovery,
depth files, and a trained model exported to one file (`workdir_export`: `export`, or
`onnx_export`; both describe it by `export_interface`) and run with JAX and numpy only
(`deploy`).
"""
