"""The simulator node (``node.SimNode``, ``skyloop sim``): its pacing and command gate,
one control step, its episodes, and the commander on the bus (``vehicle_service``)."""
