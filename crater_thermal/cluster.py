"""(being written: issue cluster)."""
