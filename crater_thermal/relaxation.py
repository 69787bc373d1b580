"""(being written: issue relaxation)."""
