"""Training and evaluation loops in process: env, gym task, collector, train,
settings, evaluate, rollout, plots."""
