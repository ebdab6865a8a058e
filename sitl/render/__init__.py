"""Pictures of a world and an episode: matplotlib scenes (``scene``) and the env's fast
video frames (``frames``)."""
