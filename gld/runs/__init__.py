"""What a run is and what it leaves behind: its options (`trainer_options`, `optimizer`,
`config`, `flow_config`), the main job's recipe and the policy every launch applies
(`recipe`), its state (`state`), and its workdir: the lock, the stored configuration,
verified checkpoints, the metrics log, and loading a trained run (`workdir`,
`trained_flow`).
"""
