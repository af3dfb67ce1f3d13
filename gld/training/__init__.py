"""The trainers: the skeleton every trainer runs (`loop`), the depth trainer (`trainer`)
and the flow network's (`flow_trainer`) on it, and a run trained once and scored
(`scored_run`), which a comparison of methods and the paper's suite share.
"""
