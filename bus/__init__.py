"""skyloop's bus package (see DESIGN.md)."""
