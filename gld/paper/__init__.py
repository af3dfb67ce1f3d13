"""The paper's experiments: the suites (`scales`) and the runs of each (`suite`, with
`rate_check` and `run_configs`), running them resumably (`runner`, over `tasks`,
`training_runs` and `result_files`), what each analysis computes (`analyses`), the report
(`report`, its `sections`, `discussion`) and the paper's own numbers (`numbers`). The
library never imports it.
"""
