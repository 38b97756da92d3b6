"""What a run says: ``markdown`` (the tables of report.md), ``plots`` (the figures) and ``html``
(report.html, self-contained and offline).
"""
