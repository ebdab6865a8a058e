"""The vehicle's physics and control: the JSBSim F450 flight model, the velocity autopilot,
the sensors and the state estimator (``vehicle.Vehicle`` puts them together)."""
