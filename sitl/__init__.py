"""skyloop's sitl package (see DESIGN.md)."""
