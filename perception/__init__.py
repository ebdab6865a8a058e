"""skyloop's perception package (see DESIGN.md)."""
