"""A log by ROS 2 conventions: the 3D view's TF, clock, path and world (``view``, with
the simulator's geometry from ``scene``) and the ``skyloop_msgs`` interface package
(``package``)."""
