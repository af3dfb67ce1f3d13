"""The networks: the global-local model and its parts (global encoder, hypernetwork,
per-example filter banks, layers), the learned flow network and the depth models built
around it, the baselines, and the registry that names them all for `--model`.
"""
