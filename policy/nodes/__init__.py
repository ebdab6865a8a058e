"""The processes on the bus: the policy node, the learner node and its settings,
actor weights over the bus."""
