"""Analysis of MLflow experiments: the paper's figures and tables (report), episode animations.

Modules: `report` (python -m analysis.report: the CLI and report.md), `data` (runs grouped into
cells, the reference baseline of each scenario, the curves of Fig. 3a), `tables`, `figures`,
`paper` (the paper's reported numbers beside ours), `export` (marl-eval JSON), `aggregate`
(rliable-style aggregates over seeds and scenarios), `stats` (every statistic the report uses),
`runs` (reading one or several MLflow experiments), `style` (figure style), `animate`
(python -m analysis.animate).
"""
