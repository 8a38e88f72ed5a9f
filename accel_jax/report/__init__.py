"""HTML report assembly from study results (private; the CLI's `report` uses it)."""
