"""The report's sections, by topic: each a function of the results the report reads
(`gld.paper.report_results.ReportResults`) that returns its Markdown and checks its
target; `gld.paper.report.write_report` puts them in order."""
