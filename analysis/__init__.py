"""Analysis of MLflow experiments: the paper's figures and tables (report), episode animations.

Modules: `report` (python -m analysis.report), `animate` (python -m analysis.animate),
`stats` (every statistic the report uses), `runs` (reading MLflow), `style` (figure style).
"""
