"""What a ground station expects of a PX4-like vehicle, each protocol in its module:
the services on connect (``services``), telemetry and its rates, parameters, missions,
goals, AUTOPILOT_VERSION and FTP. ``mavlink_bridge.vehicle_link`` carries them."""
