"""The worlds: scenarios as TOML data, world families drawn per episode, terrain, static
obstacles, moving aircraft and the collision kernels (``world.World`` puts them together)."""
