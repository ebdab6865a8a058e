"""skyloop's mavlink_bridge package (see DESIGN.md)."""
