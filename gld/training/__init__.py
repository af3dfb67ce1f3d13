"""The trainers: the depth trainer with the training loop every trainer runs
(`trainer`), and the flow network's (`flow_trainer`).
"""
