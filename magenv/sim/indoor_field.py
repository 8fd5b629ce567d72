"""A static indoor magnetic field: the Earth field plus distant ferrous structures and wiring.

The field varies in space but not in time, and is smooth in position: every
source is kept at least ``min_distance`` (≥ 1 m by default) from the region
the sensor visits. Frames and units: ENU earth frame, positions in m, field
in µT.

* Ferrous structures (steel beams, rebar, radiators, cabinets) are point
  dipoles ``B = µ0/(4π)·(3 r̂ (m·r̂) − m)/|r|³`` (``magenv.sim.magnet.dipole_field``
  gives the same formula; here it is summed over sources inside one kernel).
* DC wiring is an infinite straight wire ``B = µ0 I/(2π d) · (û × d̂)`` with û
  the wire direction and d the perpendicular offset from the wire.

:func:`random_indoor_field` places sources around a walking area and scales
each one so that its own field at the nearest point of the area has a drawn
magnitude (µT) — the knob that matters to a filter — rather than drawing
moments in A·m² directly.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from numba import njit

K_DIPOLE = 0.1  # µ0/(4π) in µT·m³/(A·m²)
K_WIRE = 0.2  # µ0/(2π) in µT·m/A


@njit(cache=True)
def field_kernel(pos, earth, d_pos, d_mom, w_pt, w_dir, w_cur, out):
    """Field (µT, ENU) at positions ``pos`` (N, 3) m into ``out`` (N, 3).

    ``earth`` (3,) µT; dipoles at ``d_pos`` (D, 3) m with moments ``d_mom``
    (D, 3) A·m²; wires through ``w_pt`` (W, 3) m along unit ``w_dir`` (W, 3)
    carrying ``w_cur`` (W,) A.
    """
    n = pos.shape[0]
    for i in range(n):
        bx, by, bz = earth[0], earth[1], earth[2]
        for k in range(d_pos.shape[0]):
            rx = pos[i, 0] - d_pos[k, 0]
            ry = pos[i, 1] - d_pos[k, 1]
            rz = pos[i, 2] - d_pos[k, 2]
            r2 = rx * rx + ry * ry + rz * rz
            r = np.sqrt(r2)
            mr = (d_mom[k, 0] * rx + d_mom[k, 1] * ry + d_mom[k, 2] * rz) / r2
            c = K_DIPOLE / (r2 * r)
            bx += c * (3.0 * mr * rx - d_mom[k, 0])
            by += c * (3.0 * mr * ry - d_mom[k, 1])
            bz += c * (3.0 * mr * rz - d_mom[k, 2])
        for k in range(w_pt.shape[0]):
            rx = pos[i, 0] - w_pt[k, 0]
            ry = pos[i, 1] - w_pt[k, 1]
            rz = pos[i, 2] - w_pt[k, 2]
            a = rx * w_dir[k, 0] + ry * w_dir[k, 1] + rz * w_dir[k, 2]
            dx, dy, dz = rx - a * w_dir[k, 0], ry - a * w_dir[k, 1], rz - a * w_dir[k, 2]
            d2 = dx * dx + dy * dy + dz * dz
            c = K_WIRE * w_cur[k] / d2  # |B| = K I / d, direction û × d/|d|
            bx += c * (w_dir[k, 1] * dz - w_dir[k, 2] * dy)
            by += c * (w_dir[k, 2] * dx - w_dir[k, 0] * dz)
            bz += c * (w_dir[k, 0] * dy - w_dir[k, 1] * dx)
        out[i, 0] = bx
        out[i, 1] = by
        out[i, 2] = bz


def _arr(x, cols) -> np.ndarray:
    a = np.ascontiguousarray(np.asarray(x, dtype=float).reshape(-1, cols))
    if not np.all(np.isfinite(a)):
        raise ValueError("indoor field: source parameters must be finite")
    return a


@dataclasses.dataclass(frozen=True, eq=False)
class IndoorField:
    """Earth field + dipoles + straight wires; call it with positions (N, 3) m → field (N, 3) µT, ENU.

    Attributes:
        earth: (3,) undisturbed Earth field, µT, ENU.
        dipole_pos: (D, 3) m. dipole_moment: (D, 3) A·m².
        wire_point: (W, 3) a point of each wire, m. wire_dir: (W, 3) unit directions.
        wire_current: (W,) A.
    """

    earth: np.ndarray
    dipole_pos: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 3)))
    dipole_moment: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 3)))
    wire_point: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 3)))
    wire_dir: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 3)))
    wire_current: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))

    def __post_init__(self) -> None:
        set_ = lambda k, v: object.__setattr__(self, k, v)
        set_("earth", _arr(self.earth, 3).reshape(3))
        for k in ("dipole_pos", "dipole_moment", "wire_point", "wire_dir"):
            set_(k, _arr(getattr(self, k), 3))
        set_("wire_current", np.ascontiguousarray(np.asarray(self.wire_current, float).reshape(-1)))
        if len(self.dipole_pos) != len(self.dipole_moment):
            raise ValueError("IndoorField: dipole_pos and dipole_moment must have the same number of rows")
        if not (len(self.wire_point) == len(self.wire_dir) == len(self.wire_current)):
            raise ValueError("IndoorField: wire_point, wire_dir and wire_current must have the same length")
        norms = np.linalg.norm(self.wire_dir, axis=1)
        if np.any(np.abs(norms - 1.0) > 1e-9):
            raise ValueError(f"IndoorField: wire_dir rows must be unit vectors, got norms {norms}")

    def __call__(self, pos) -> np.ndarray:
        pos = np.ascontiguousarray(np.asarray(pos, dtype=float))
        if pos.ndim != 2 or pos.shape[1] != 3 or not np.all(np.isfinite(pos)):
            raise ValueError(f"IndoorField: positions must be a finite (N, 3) array in m, got shape {pos.shape}")
        out = np.empty_like(pos)
        field_kernel(
            pos, self.earth, self.dipole_pos, self.dipole_moment, self.wire_point, self.wire_dir, self.wire_current, out
        )
        return out

    def min_source_distance(self, pos) -> float:
        """Smallest distance (m) from any of ``pos`` (N, 3) to any source (dipole or wire)."""
        pos = np.asarray(pos, float).reshape(-1, 3)
        best = np.inf
        if len(self.dipole_pos):
            best = min(best, float(np.min(np.linalg.norm(pos[:, None] - self.dipole_pos[None], axis=2))))
        for p0, u in zip(self.wire_point, self.wire_dir):
            r = pos - p0
            best = min(best, float(np.min(np.linalg.norm(r - (r @ u)[:, None] * u, axis=1))))
        return best


def random_indoor_field(
    rng: np.random.Generator,
    earth,
    area_points,
    n_dipoles=(3, 6),
    strength_ut=(2.0, 12.0),
    distance_m=(1.0, 3.0),
    n_wires=(0, 2),
    wire_current_a=(1.0, 15.0),
    ceiling_m=2.7,
) -> IndoorField:
    """A random static indoor field around the positions ``area_points`` (M, 3) m the sensor will visit.

    Each dipole is placed at a drawn distance (``distance_m``) from a random
    visited point — below the floor, in a wall beside it, or overhead — and
    pushed out until no visited point is closer than ``distance_m[0]``; its
    moment (random direction) is scaled so that its own field at the nearest
    visited point is ``strength_ut`` (µT, drawn). Wires run horizontally at
    ``ceiling_m`` (m) in a random direction with a drawn current (A, random
    sign). Ranges are (low, high) pairs, integer counts inclusive.
    """
    pts = np.asarray(area_points, float).reshape(-1, 3)
    if len(pts) == 0:
        raise ValueError("random_indoor_field needs at least one area point")
    d_min = float(distance_m[0])
    nd = int(rng.integers(n_dipoles[0], n_dipoles[1] + 1))
    d_pos, d_mom = np.zeros((nd, 3)), np.zeros((nd, 3))
    for k in range(nd):
        anchor = pts[int(rng.integers(len(pts)))]
        direction = rng.normal(size=3)
        direction[2] = -abs(direction[2]) if rng.uniform() < 0.5 else direction[2]  # half below, rest anywhere
        direction /= np.linalg.norm(direction)
        d = float(rng.uniform(*distance_m))
        p = anchor + d * direction
        for _ in range(200):  # push away until every visited point is at least d_min away
            dist = np.linalg.norm(pts - p, axis=1)
            j = int(np.argmin(dist))
            if dist[j] >= d_min:
                break
            p = pts[j] + (p - pts[j]) / max(dist[j], 1e-9) * d_min * 1.05
        r = float(np.min(np.linalg.norm(pts - p, axis=1)))
        m_dir = rng.normal(size=3)
        m_dir /= np.linalg.norm(m_dir)
        b = float(rng.uniform(*strength_ut))
        d_pos[k] = p
        near = pts[int(np.argmin(np.linalg.norm(pts - p, axis=1)))]
        cos_t = float(m_dir @ (near - p)) / r  # |B| = K·|m|/r³·sqrt(1 + 3cos²θ) at the nearest point
        d_mom[k] = m_dir * b * r**3 / (K_DIPOLE * np.sqrt(1.0 + 3.0 * cos_t**2))
    nw = int(rng.integers(n_wires[0], n_wires[1] + 1))
    w_pt, w_dir = np.zeros((nw, 3)), np.zeros((nw, 3))
    w_cur = np.zeros(nw)
    centre = pts.mean(axis=0)
    span = np.ptp(pts[:, :2], axis=0) + 2.0
    for k in range(nw):
        ang = rng.uniform(0, np.pi)
        w_dir[k] = (np.cos(ang), np.sin(ang), 0.0)
        w_pt[k] = (
            centre[0] + rng.uniform(-0.5, 0.5) * span[0],
            centre[1] + rng.uniform(-0.5, 0.5) * span[1],
            ceiling_m,
        )
        w_cur[k] = rng.uniform(*wire_current_a) * rng.choice((-1.0, 1.0))
    return IndoorField(np.asarray(earth, float), d_pos, d_mom, w_pt, w_dir, w_cur)
