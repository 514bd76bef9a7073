"""Frames and angles shared by the compass and the inclinometer (pure numpy-free math).

Body frame FLU: x forward, y left, z up.  World frame NWU: x north, y west, z up.  Heading is
clockwise from north, pitch positive nose up, roll positive right side down, all in degrees.
Body to world: ``R = Rz(-heading) @ Ry(-pitch) @ Rx(roll)``; a body sensor reads ``R.T @ v_world``.
An accelerometer at rest reads the reaction to gravity, ``(0, 0, +g)`` in the world frame.
"""

from __future__ import annotations

import math

Vec3 = tuple[float, float, float]
Mat3 = tuple[float, float, float, float, float, float, float, float, float]


def _rx(a: float) -> Mat3:
    c, s = math.cos(a), math.sin(a)
    return (1.0, 0.0, 0.0, 0.0, c, -s, 0.0, s, c)


def _ry(a: float) -> Mat3:
    c, s = math.cos(a), math.sin(a)
    return (c, 0.0, s, 0.0, 1.0, 0.0, -s, 0.0, c)


def _rz(a: float) -> Mat3:
    c, s = math.cos(a), math.sin(a)
    return (c, -s, 0.0, s, c, 0.0, 0.0, 0.0, 1.0)


def matmul(a: Mat3, b: Mat3) -> Mat3:
    return tuple(  # type: ignore[return-value]
        sum(a[3 * i + k] * b[3 * k + j] for k in range(3)) for i in range(3) for j in range(3)
    )


def matvec(m: Mat3, v: Vec3) -> Vec3:
    return (
        m[0] * v[0] + m[1] * v[1] + m[2] * v[2],
        m[3] * v[0] + m[4] * v[1] + m[5] * v[2],
        m[6] * v[0] + m[7] * v[1] + m[8] * v[2],
    )


def transpose(m: Mat3) -> Mat3:
    return (m[0], m[3], m[6], m[1], m[4], m[7], m[2], m[5], m[8])


def body_to_world(heading_deg: float, pitch_deg: float, roll_deg: float) -> Mat3:
    h, p, r = (math.radians(x) for x in (heading_deg, pitch_deg, roll_deg))
    return matmul(_rz(-h), matmul(_ry(-p), _rx(r)))


def world_to_body(v_world: Vec3, heading_deg: float, pitch_deg: float, roll_deg: float) -> Vec3:
    return matvec(transpose(body_to_world(heading_deg, pitch_deg, roll_deg)), v_world)


def tilt_from_accel(a: Vec3) -> tuple[float, float]:
    """(pitch_deg, roll_deg) from a resting accelerometer's body reading (any unit)."""
    ax, ay, az = a
    if ax == 0.0 and ay == 0.0 and az == 0.0:
        raise ValueError("zero acceleration vector: no tilt")
    pitch = math.degrees(math.atan2(ax, math.hypot(ay, az)))
    roll = math.degrees(math.atan2(ay, az))
    return pitch, roll


def tilt_compensated_heading(m_body: Vec3, pitch_deg: float, roll_deg: float) -> float:
    """Heading (deg, clockwise from the field's north) of a calibrated body magnetometer reading."""
    p, r = math.radians(pitch_deg), math.radians(roll_deg)
    lev = matvec(matmul(_ry(-p), _rx(r)), m_body)
    if lev[0] == 0.0 and lev[1] == 0.0:
        raise ValueError("no horizontal magnetic field component")
    return math.degrees(math.atan2(lev[1], lev[0])) % 360.0
