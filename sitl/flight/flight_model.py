"""JSBSim F450 quadrotor flight model: the one place where feet, NED and geodetic meet SI/ENU.

Implements the physics side of skyloop's vehicle (issue 2, section 2):

- Airframe: JSBSim's own F450 (``<jsbsim root>/aircraft/F450``): its metrics, mass,
  gear, propulsion (four DJI E305 motors with DJI 9450 props), effectors (ESC actuators)
  and aerodynamics files, loaded unchanged.  JSBSim integrates the rigid body, the motor
  and propeller dynamics; there is no hand-written integrator here.
- Inner loops: ``sitl/flight/fcs/f450_attitude_rate.xml`` replaces the F450's
  ``FlightControl.xml``.  It keeps that file's body-rate PID gains and quad-X mixer, adds
  a PX4-style attitude P loop fed by a tilt vector, and drops the 0.75 rad/s cap that
  FlightControl.xml puts on rate references (yaw rates up to 2 rad/s must be reachable).
  All of it runs inside JSBSim at every physics step (1/500 s), so Python only sets four
  properties at the outer-loop rate (``set_commands``).
- Force balance, measured (and checked in tests/sitl/test_flight_model.py): the hover
  collective is 0.4068 (specific force = g at sea level), not the 0.45-0.5 once noted;
  with altitude held, a steady 10 deg tilt accelerates at ~0.97 g tan(10 deg) (20 deg:
  ~0.95, body drag growing with speed), i.e. the rigid-body relation holds once the
  attitude loop tracks the tilt exactly.
- The F450's ``Sensor*.xml`` systems (JSBSim's own sensor models) are not loaded; skyloop
  models its sensors in :mod:`sitl.flight.sensors`.  Without them, and with the aircraft file
  declared at the version this JSBSim expects, loading prints nothing (the stock F450
  prints "INCOMPATIBLE CFG FILE" and "Failed to tie property" lines); the debug level is
  also set to 0 before the executive is built, which silences JSBSim's banner.
- Placement: world ENU metres map to geodetic latitude/longitude around the origin
  (0 deg, 0 deg) with the WGS84 meridian and prime-vertical radii; up is JSBSim's height
  above its own ground (which is at 0 m).  Over a few hundred metres the flat-earth mapping
  errs by well under a millimetre.  Every reset starts JSBSim exactly at that origin and
  adds the start's east/north offset in Python: JSBSim's initial-condition setters
  recompute from the previous initial condition, so setting any other latitude would leak
  the previous episode's rounding into the next one, whereas at (0, 0) the geodetic
  conversions are exact and every reset with the same inputs is bit-identical.  ``reset``
  places the vehicle airborne with zero velocity and level attitude, and spins the
  propellers up to the hover throttle with JSBSim's propagation disabled, so it starts
  hovering.
- Ground: JSBSim's ground is flat, at ``ground`` metres (0 unless told otherwise).
  ``reset(..., on_ground=True)`` puts the vehicle on its gear there, motors stopped (the
  F450's CG rests ``REST_HEIGHT`` above the ground); :meth:`FlightModel.set_ground` moves
  the ground under the vehicle (the simulator node makes it follow the world's terrain
  while the commander flies near it). Reported heights are ``h_agl + ground``, which is
  exactly ``h_agl`` when the ground is at 0 (every episode of the env).
"""

from __future__ import annotations

import math
import os
import tempfile
from pathlib import Path

import jsbsim

FT = 0.3048  # metres per foot
REST_HEIGHT = 0.1507  # m, CG above the ground with the F450 standing on its gear (measured)
FCS_FILE = Path(__file__).resolve().parent / "fcs" / "f450_attitude_rate.xml"

_WGS84_A = 6378137.0
_WGS84_E2 = 6.69437999014e-3
_EARTH_RATE = 7.292115e-5  # rad/s

_AIRCRAFT_TEMPLATE = """<?xml version="1.0"?>
<fdm_config name="F450-skyloop" version="2.0" release="ALPHA">
  <fileheader/>
  <metrics file="{f450}/Metrics.xml"/>
  <mass_balance file="{f450}/Mass.xml"/>
  <ground_reactions file="{f450}/Gear.xml"/>
  <propulsion file="{f450}/Propulsion.xml"/>
  <system file="{fcs}"/>
  <system file="{f450}/Effectors.xml"/>
  <aerodynamics file="{f450}/Aero.xml"/>
</fdm_config>
"""


def _radii(lat: float) -> tuple[float, float]:
    """WGS84 meridian (north) and prime-vertical (east) radii of curvature at `lat`."""
    s2 = math.sin(lat) ** 2
    w = math.sqrt(1.0 - _WGS84_E2 * s2)
    return _WGS84_A * (1.0 - _WGS84_E2) / w**3, _WGS84_A / w


_M_PER_RAD_LAT, _M_PER_RAD_LON = _radii(0.0)  # at the origin (0 deg, 0 deg)


def load_f450(dt: float) -> jsbsim.FGFDMExec:
    """Build a silent JSBSim executive holding the F450 with skyloop's inner loops."""
    root = jsbsim.get_default_root_dir()
    f450 = os.path.join(root, "aircraft", "F450")
    jsbsim.FGJSBBase().debug_lvl = 0  # before the executive exists: no banner
    fdm = jsbsim.FGFDMExec(root)
    fdm.set_debug_level(0)
    with tempfile.TemporaryDirectory(prefix="skyloop-f450-") as tmp:
        model_dir = Path(tmp) / "F450skyloop"
        model_dir.mkdir()
        (model_dir / "F450skyloop.xml").write_text(
            _AIRCRAFT_TEMPLATE.format(f450=f450, fcs=FCS_FILE)
        )
        ok = fdm.load_model_with_paths(
            "F450skyloop", tmp, os.path.join(root, "engine"), os.path.join(root, "systems"), True
        )
    if not ok:
        raise RuntimeError("JSBSim could not load the F450 model")
    fdm.set_dt(dt)
    return fdm


class FlightModel:
    """JSBSim F450 stepped at a fixed physics rate; inputs and outputs in SI and world ENU.

    Commands (held between calls to `set_commands`): the horizontal tilt vector (tangent of
    the tilt, i.e. desired horizontal acceleration over vertical), the collective throttle
    in [0, 1] and the world yaw rate (ENU, counter-clockwise positive).
    """

    def __init__(self, physics_hz: float = 500.0, hover_throttle: float = 0.4068,
                 spinup_time: float = 0.5) -> None:
        self.dt = 1.0 / physics_hz
        self.hover_throttle = hover_throttle
        self.spinup_steps = max(1, round(spinup_time * physics_hz))
        self.fdm = load_f450(self.dt)
        self._run = self.fdm.run
        pm = self.fdm.get_property_manager()

        def node(name: str):
            n = pm.get_node(name)
            if n is None:
                raise KeyError(name)
            return n

        self._set_tilt_n = node("skyloop/tilt-north").set_double_value
        self._set_tilt_e = node("skyloop/tilt-east").set_double_value
        self._set_thr = node("skyloop/throttle-cmd").set_double_value
        self._set_psidot = node("skyloop/psi-dot-cmd-rps").set_double_value
        self._propagate = node("simulation/models/FGPropagate/enabled")
        g = {
            name: node(prop).get_double_value
            for name, prop in {
                "lat": "position/lat-geod-rad", "lon": "position/long-gc-rad",
                "h": "position/h-agl-ft",
                "vn": "velocities/v-north-fps", "ve": "velocities/v-east-fps",
                "vd": "velocities/v-down-fps",
                "phi": "attitude/phi-rad", "theta": "attitude/theta-rad",
                "psi": "attitude/psi-rad",
                "p": "velocities/pi-rad_sec", "q": "velocities/qi-rad_sec",
                "r": "velocities/ri-rad_sec",
                "fx": "accelerations/a-pilot-x-ft_sec2", "fy": "accelerations/a-pilot-y-ft_sec2",
                "fz": "accelerations/a-pilot-z-ft_sec2",
                "grav": "accelerations/gravity-ft_sec2",
            }.items()
        }
        self._g = g
        self.gravity = 9.80665  # effective (gravity minus centrifugal), set by reset
        self._east0 = self._north0 = 0.0  # world position of JSBSim's origin this episode
        self._ground = 0.0  # m, JSBSim's (flat) ground elevation
        self._set_ground = node("position/terrain-elevation-asl-ft").set_double_value
        self.reset(0.0, 0.0, 3.5, 0.0)

    # ------------------------------------------------------------------ placement
    def reset(self, east: float, north: float, up: float, yaw: float,
              on_ground: bool = False) -> None:
        """Hovering at ENU (east, north, up) metres with ENU yaw `yaw`, zero velocity;
        ``on_ground``: standing on flat ground at ``up`` metres instead, motors stopped."""
        fdm = self.fdm
        self._east0, self._north0 = float(east), float(north)
        self._ground = float(up) if on_ground else 0.0
        fdm["ic/lat-geod-rad"] = 0.0
        fdm["ic/long-gc-rad"] = 0.0
        fdm["ic/terrain-elevation-ft"] = self._ground / FT
        fdm["ic/h-agl-ft"] = (REST_HEIGHT if on_ground else up) / FT
        for name in ("ic/u-fps", "ic/v-fps", "ic/w-fps", "ic/p-rad_sec", "ic/q-rad_sec",
                     "ic/r-rad_sec", "ic/phi-rad", "ic/theta-rad"):
            fdm[name] = 0.0
        fdm["ic/psi-true-rad"] = (0.5 * math.pi - yaw) % (2.0 * math.pi)
        fdm.reset_to_initial_conditions(0)
        fdm["propulsion/set-running"] = -1
        if on_ground:  # motors stopped; let it settle on its gear
            self.set_commands(0.0, 0.0, 0.0, 0.0)
            self.run(self.spinup_steps)
            self.gravity = self._g["grav"]() * FT - _EARTH_RATE**2 * _M_PER_RAD_LON
            return
        self.set_commands(0.0, 0.0, self.hover_throttle, 0.0)
        # spin the propellers up to hover speed with the vehicle frozen in place
        self._propagate.set_double_value(0.0)
        for _ in range(self.spinup_steps):
            self._run()
        self._propagate.set_double_value(1.0)
        self.gravity = self._g["grav"]() * FT - _EARTH_RATE**2 * _M_PER_RAD_LON

    @property
    def ground(self) -> float:
        """Elevation (m) of JSBSim's flat ground."""
        return self._ground

    def set_ground(self, elevation: float) -> None:
        """Move JSBSim's flat ground to ``elevation`` metres (heights keep their meaning)."""
        self._ground = float(elevation)
        self._set_ground(self._ground / FT)

    # ------------------------------------------------------------------ stepping
    def set_commands(self, tilt_east: float, tilt_north: float, throttle: float,
                     yaw_rate: float) -> None:
        """Inner-loop inputs: tilt vector (ENU), collective [0, 1], ENU yaw rate (rad/s)."""
        self._set_tilt_e(tilt_east)
        self._set_tilt_n(tilt_north)
        self._set_thr(throttle)
        self._set_psidot(-yaw_rate)  # NED heading rate is clockwise positive

    def run(self, steps: int) -> None:
        """Advance `steps` physics steps."""
        run = self._run
        for _ in range(steps):
            run()

    # ------------------------------------------------------------------ truth
    def position(self) -> tuple[float, float, float]:
        """ENU position, metres."""
        g = self._g
        return (self._east0 + g["lon"]() * _M_PER_RAD_LON,
                self._north0 + g["lat"]() * _M_PER_RAD_LAT,
                g["h"]() * FT + self._ground)

    def velocity(self) -> tuple[float, float, float]:
        """ENU velocity relative to the ground, m/s."""
        g = self._g
        return g["ve"]() * FT, g["vn"]() * FT, -g["vd"]() * FT

    def euler_ned(self) -> tuple[float, float, float]:
        """JSBSim's (phi, theta, psi): roll, pitch (nose up +), heading (clockwise from N)."""
        g = self._g
        return g["phi"](), g["theta"](), g["psi"]()

    def rpy(self) -> tuple[float, float, float]:
        """ENU/FLU roll, pitch (nose down +), yaw (CCW from east); see `enu_rpy`."""
        g = self._g
        return enu_rpy(g["phi"](), g["theta"](), g["psi"]())

    def gyro_flu(self) -> tuple[float, float, float]:
        """Inertial body rates in the FLU body frame, rad/s."""
        g = self._g
        return g["p"](), -g["q"](), -g["r"]()

    def specific_force_flu(self) -> tuple[float, float, float]:
        """What an ideal accelerometer at the CG reads (FLU body frame), m/s^2."""
        g = self._g
        return g["fx"]() * FT, -g["fy"]() * FT, -g["fz"]() * FT


def rotation_flu_to_enu(phi: float, theta: float, psi: float) -> list[list[float]]:
    """Body(FLU)->world(ENU) rotation from JSBSim's NED Euler angles (phi, theta, psi)."""
    cf, sf = math.cos(phi), math.sin(phi)
    ct, st = math.cos(theta), math.sin(theta)
    cp, sp = math.cos(psi), math.sin(psi)
    # NED <- FRD, rows N, E, D; columns x (fwd), y (right), z (down)
    n = (ct * cp, sf * st * cp - cf * sp, cf * st * cp + sf * sp)
    e = (ct * sp, sf * st * sp + cf * cp, cf * st * sp - sf * cp)
    d = (-st, sf * ct, cf * ct)
    # ENU <- FLU: rows (E, N, -D), columns (x, -y, -z)
    return [[e[0], -e[1], -e[2]], [n[0], -n[1], -n[2]], [-d[0], d[1], d[2]]]


def enu_rpy(phi: float, theta: float, psi: float) -> tuple[float, float, float]:
    """ENU/FLU roll, pitch, yaw (ZYX; pitch nose-down positive, yaw CCW from east).

    Roll keeps its sign between FRD and FLU, pitch flips, and yaw = pi/2 - heading.
    """
    yaw = math.remainder(0.5 * math.pi - psi, 2.0 * math.pi)
    return phi, -theta, yaw
