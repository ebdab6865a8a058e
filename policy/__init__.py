"""skyloop's policy package (see DESIGN.md), in four parts:

- ``algorithms``: the learning cores and controllers; pure, no processes.
- ``training``: training and evaluation loops in process (env, train, evaluate).
- ``logs``: training from episode logs (MCAP): transitions, assembly, offline.
- ``nodes``: the processes on the bus: the policy node, the learner, weights.

``shipped``: the actors skyloop ships, by name (``--policy shipped:NAME``).
"""
