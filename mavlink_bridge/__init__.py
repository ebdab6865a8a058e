"""skyloop's MAVLink face (see DESIGN.md, "MAVLink conventions" and "Frames and units").

Pure cores: :mod:`~mavlink_bridge.frames` (the one ENU/FLU <-> NED/FRD conversion),
:mod:`~mavlink_bridge.modes` (PX4 custom modes), :mod:`~mavlink_bridge.validate`
(setpoint validation), :mod:`~mavlink_bridge.interfaces` (what the bridge exchanges with
the vehicle: ``VelocityCommand``, ``VehicleTelemetry``, ``CommanderLike``).
UDP endpoints: :mod:`~mavlink_bridge.vehicle_link` (the vehicle, PX4 SITL ports) and
:mod:`~mavlink_bridge.offboard_client` (the companion computer / policy side), both over
:mod:`~mavlink_bridge.transport`.
"""
