"""skyloop's policy package (see DESIGN.md)."""
