"""The simulated vehicle and its worlds (see DESIGN.md).

``episode.EpisodeSim`` is the episode core the in-process env and the sim node share; it
puts together a world (``world/``), the vehicle (``flight/``) and the LiDAR (``lidar/``).
``commander/`` is the vehicle's mode logic, ``node/`` the sim node on the bus, ``render/``
pictures of worlds and episodes.
"""
