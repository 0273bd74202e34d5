"""Command-line options of the PX4 bridge (``python -m services bridge --help``)."""

from __future__ import annotations

import argparse

from services import options

DEFAULT_URL = "udpin://0.0.0.0:14540"
#: The allowed box, ENU metres: also what a ``--trajectory`` is checked against in the
#: sim profile.
DEFAULT_GEOFENCE = "-5,5,-5,5,-0.5,4"


#: The connection kinds of a MAVSDK URL.
URL_SCHEMES = ("udpin", "udpout", "tcpin", "tcpout", "serial")


def mavlink_url(text: str) -> str:
    """argparse ``type=``: a MAVSDK connection URL (``udpout://HOST:PORT``, ...)."""
    scheme, sep, rest = text.partition("://")
    if not sep or scheme not in URL_SCHEMES or not rest:
        raise argparse.ArgumentTypeError(
            f"not a MAVSDK URL: {text!r} (e.g. udpout://127.0.0.1:14550; kinds: "
            f"{', '.join(URL_SCHEMES)})"
        )
    return text


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The bridge's own options, added to the services' common parser."""
    p.add_argument(
        "--connect",
        default=DEFAULT_URL,
        help="MAVSDK connection URL, e.g. udpin://0.0.0.0:14540 or serial:///dev/ttyACM0:921600",
    )
    p.add_argument(
        "--forward",
        action="append",
        type=mavlink_url,
        default=[],
        metavar="URL",
        help="also pass every MAVLink message between PX4 and this MAVSDK URL, both ways "
        "(repeatable), so that a ground station watches the vehicle while the stack flies "
        "it, e.g. udpout://127.0.0.1:14550 for QGroundControl on this machine "
        "(default: none)",
    )
    p.add_argument(
        "--vehicle-file",
        default=None,
        help="vehicle file (maximum thrust, rate limits); default: the shipped one",
    )
    p.add_argument(
        "--connect-timeout",
        type=float,
        default=30.0,
        help="longest wait for an autopilot heartbeat [s]",
    )
    p.add_argument(
        "--health-timeout",
        type=float,
        default=60.0,
        help="longest wait for PX4 to be healthy and armable [s]",
    )
    p.add_argument(
        "--command-timeout",
        type=float,
        default=3.0,
        help="longest wait for PX4 to accept offboard / answer a mode command [s]",
    )
    p.add_argument(
        "--setpoint-timeout",
        type=float,
        default=0.3,
        help="leave offboard when no setpoint arrived for this long [s]",
    )
    p.add_argument(
        "--min-stream",
        type=float,
        default=1.0,
        help="arm only after setpoints streamed this long without a gap [s]",
    )
    p.add_argument(
        "--failsafe",
        choices=("hold", "land"),
        default="hold",
        help="what PX4 does when setpoints stop",
    )
    p.add_argument(
        "--max-send-errors",
        type=int,
        default=3,
        help="leave offboard (--failsafe) after this many setpoints in a row failed to "
        "reach MAVSDK",
    )
    p.add_argument(
        "--geofence",
        default=DEFAULT_GEOFENCE,
        help="xmin,xmax,ymin,ymax,zmin,zmax of the allowed box, ENU metres",
    )
    p.add_argument(
        "--geofence-action",
        choices=("hold", "land"),
        default="hold",
        help="what PX4 does when the vehicle leaves the box",
    )
    p.add_argument(
        "--max-throttle",
        type=float,
        default=1.0,
        help="upper clamp of the normalised thrust sent to PX4 (0, 1]",
    )
    p.add_argument(
        "--vision",
        choices=("odometry", "mocap", "off"),
        default="odometry",
        help="forward mocap to PX4 as ODOMETRY for EKF2 (estimator type vision), "
        "as mocap-type ODOMETRY, or not at all",
    )
    options.add_mocap_source_argument(p)
    options.add_mocap_body_argument(p)
    p.add_argument(
        "--vision-frame",
        choices=("local_frd", "mocap_ned"),
        default="local_frd",
        help="ODOMETRY world frame id (local_frd: heading arbitrary)",
    )
    p.add_argument(
        "--no-require-local-position",
        dest="require_local_position",
        action="store_false",
        help="be ready without PX4 reporting a local position",
    )
    p.add_argument(
        "--no-start-mission",
        dest="start_mission",
        action="store_false",
        help="do not send the controller's 'start' command when engaged",
    )
    p.add_argument(
        "--takeoff-timeout",
        type=float,
        default=30.0,
        help="longest wait for PX4's take-off (arm command with takeoff_m) [s]",
    )
    p.add_argument(
        "--status-rate", type=float, default=2.0, help="vehicle_status events per second (0: none)"
    )
    p.add_argument(
        "--imu",
        choices=("px4", "off"),
        default="px4",
        help="publish PX4's body rates as imu at the control rate (the estimator's "
        "clock), or not (a simulator on the bus does it)",
    )
    p.add_argument(
        "--max-gyro-age",
        type=float,
        default=0.2,
        help="older PX4 rate telemetry is not published as imu [s]",
    )
