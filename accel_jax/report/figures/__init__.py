"""The figures of the commands and the report: data in, a matplotlib `Figure` (or a PNG
written whole) out: `identification` (`accel-jax identify --plot`), `noise` (`accel-jax
noise --plot`), `diagnosis` (`accel-jax diagnose --plot`, one record or a set). With the
study plumbing (`report/_study.py`), the only place that imports matplotlib."""
