"""skyloop's policy package (see DESIGN.md), in four parts:

- ``algorithms``: the learning cores and controllers; pure, no processes.
- ``training``: training and evaluation loops in process (env, train, evaluate).
- ``logs``: training from episode logs (MCAP): transitions, assembly, offline.
- ``nodes``: the processes on the bus: the policy node, the learner, weights.

``policy/shipped/`` holds the shipped actor (``training.evaluate.SHIPPED_POLICY``).
"""
