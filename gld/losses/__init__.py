"""Training losses: the sparse supervised loss with its smoothness, epipolar and
pose-teacher terms (`supervised`), and the self-supervised photometric loss
(`photometric`).
"""
