"""The paper's experiments: the runs of each suite (`suite`), running them
resumably (`runner`), what each analysis computes (`analyses`), the report
(`report`) and the paper's own numbers (`numbers`). The library never imports it.
"""
