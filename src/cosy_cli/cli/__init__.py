"""Click commands over the stage modules (no logic here)."""
