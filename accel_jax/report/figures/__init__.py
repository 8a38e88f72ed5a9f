"""The figures of the commands and the report: data in, a matplotlib `Figure` (or a PNG
written whole) out. The one place below the entry points that imports matplotlib, beside
the study plumbing (`report/_study.py`) and the diagnosis's figures (`diagnose/report.py`,
still to move)."""
