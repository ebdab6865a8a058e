"""Training from episode logs (MCAP): transitions, episode assembly, offline
training, logging in-process runs in the stack's log format."""
