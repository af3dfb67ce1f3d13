"""What a run is and what it leaves behind: its options (`options`, `config`,
`flow_config`), its state (`state`), and its workdir: the lock, the stored
configuration, verified checkpoints, the metrics log, and loading a trained run
(`workdir`, `trained_flow`).
"""
