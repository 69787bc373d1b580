"""(being written: issue inversion)."""
