"""The learning cores and controllers: TD3, DDPG, networks, agents, ABR, rewards,
replay, the scripted baseline. Pure: no processes, no bus."""
