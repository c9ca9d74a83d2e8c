"""Annotated objects of the synthetic world: shapes (boxes in the object's own frame) and instance colours.

``make_agent(kind, rng, origin, heading, speed, attribute)`` builds one ``world.Agent``. The object frame is
x forward, y left, z up, origin on the ground under the centre of the annotation box; every part lies inside the
annotation box (w, l, h) centred at (0, 0, h/2).
"""
from __future__ import annotations

import numpy as np

from occflownet.synth.materials import MATERIALS, TEX_DARK, TEX_GLASS, TEX_PLAIN, TEX_STRIPES
from occflownet.synth.world import Agent

GLASS = (0.16, 0.20, 0.26)
TYRE = (0.08, 0.08, 0.09)
SKIN = (0.85, 0.65, 0.50)

# Kinds that are vehicles (nuScenes attribute family "vehicle.*"), cycles, pedestrians, or movable objects.
VEHICLES = ("car", "truck", "bus", "trailer", "construction")
CYCLES = ("motorcycle", "bicycle")


def instance_color(base, rng: np.random.Generator) -> np.ndarray:
    """A per-instance variation of a class colour: brightness ×[0.75, 1.15], each channel ±0.06."""
    c = np.asarray(base) * rng.uniform(0.75, 1.15) + rng.uniform(-0.06, 0.06, 3)
    return np.clip(c, 0.02, 1.0)


def _part(parts, cx, cy, z0, z1, length, width, color, texture=TEX_PLAIN):
    parts.append(((cx, cy, (z0 + z1) / 2), (length / 2, width / 2, (z1 - z0) / 2), color, texture))


def _shape(kind: str, rng: np.random.Generator, attribute: str):
    """(w, l, h) and parts [(center, half, color, texture)] of one object of ``kind``."""
    body = instance_color(MATERIALS[kind].color, rng)
    p: list = []
    if kind in VEHICLES:
        l, w, h = _vehicle_parts(p, kind, rng, body)
    elif kind in _SMALL_KINDS:
        l, w, h = _small_parts(p, kind, rng, body, attribute)
    else:
        raise ValueError(f"unknown agent kind {kind!r}")
    return (w, l, h), p


def _vehicle_parts(p: list, kind: str, rng: np.random.Generator, body) -> tuple[float, float, float]:
    """Parts of a car, truck, bus, trailer or construction vehicle appended to ``p``; returns (l, w, h)."""
    if kind == "car":
        l, w, h = rng.uniform(3.9, 4.9), rng.uniform(1.75, 2.0), rng.uniform(1.45, 1.75)
        hb = 0.6 * h
        _part(p, 0, 0, 0.0, 0.32, l - 0.7, w - 0.2, TYRE, TEX_DARK)
        _part(p, 0, 0, 0.32, hb, l, w, body)
        _part(p, -0.08 * l, 0, hb, h, 0.55 * l, w - 0.16, GLASS, TEX_GLASS)
    elif kind == "truck":
        l, w, h = rng.uniform(6.0, 9.0), rng.uniform(2.3, 2.5), rng.uniform(2.8, 3.6)
        _part(p, 0, 0, 0.0, 0.9, l - 1.0, w - 0.3, TYRE, TEX_DARK)
        _part(p, l / 2 - 1.1, 0, 0.9, 0.62 * h, 2.2, w, body)
        _part(p, l / 2 - 1.0, 0, 0.62 * h, 0.85 * h, 2.0, w - 0.1, GLASS, TEX_GLASS)
        cargo = np.clip(body * 0.5 + 0.45, 0, 1)
        _part(p, -1.25, 0, 0.9, h, l - 2.5, w, cargo)
    elif kind == "bus":
        l, w, h = rng.uniform(10.0, 12.5), 2.55, rng.uniform(3.0, 3.4)
        _part(p, 0, 0, 0.0, 0.4, l - 2.0, w - 0.3, TYRE, TEX_DARK)
        _part(p, 0, 0, 0.4, h, l, w, body, MATERIALS["bus"].texture)
    elif kind == "trailer":
        l, w, h = rng.uniform(6.0, 11.0), 2.5, rng.uniform(3.0, 3.8)
        _part(p, -l / 4, 0, 0.0, 1.0, l / 2, w - 0.3, TYRE, TEX_DARK)
        _part(p, 0, 0, 1.0, h, l, w, body)
    else:  # construction
        l, w, h = rng.uniform(5.5, 7.0), 2.6, rng.uniform(3.0, 3.5)
        _part(p, -0.1 * l, 0, 0.0, 0.9, 0.7 * l, w, TYRE, TEX_DARK)
        _part(p, -0.1 * l, 0, 0.9, 2.0, 0.7 * l, w - 0.2, body)
        _part(p, -0.2 * l, 0.3, 2.0, h, 1.8, 1.6, GLASS, TEX_GLASS)
        _part(p, 0.3 * l - 0.1, -0.4, 2.2, 2.7, 0.4 * l, 0.4, body * 0.8)
        _part(p, l / 2 - 0.4, 0, 0.2, 1.2, 0.8, w, body * 0.7)
    return l, w, h


_SMALL_KINDS = ("motorcycle", "bicycle", "pedestrian", "barrier", "traffic_cone", "pushable")


def _small_parts(p: list, kind: str, rng: np.random.Generator, body, attribute: str) -> tuple[float, float, float]:
    """Parts of a cycle, a pedestrian or a movable object appended to ``p``; returns (l, w, h)."""
    if kind == "motorcycle":
        l, w, h = rng.uniform(1.9, 2.3), rng.uniform(0.7, 0.9), rng.uniform(1.4, 1.6)
        _part(p, 0, 0, 0.0, 0.95, l, 0.4, body)
        _part(p, -0.15, 0, 0.95, h, 0.5, w, body * 0.5)
    elif kind == "bicycle":
        rider = attribute == "cycle.with_rider"
        l, w, h = rng.uniform(1.6, 1.85), 0.6, (rng.uniform(1.6, 1.8) if rider else 1.05)
        _part(p, 0, 0, 0.0, 1.05, l, 0.3, body)
        if rider:
            _part(p, -0.1, 0, 1.05, h, 0.5, w, body * 0.6)
    elif kind == "pedestrian":
        l, w, h = rng.uniform(0.35, 0.5), rng.uniform(0.55, 0.7), rng.uniform(1.55, 1.9)
        legs = instance_color((0.25, 0.22, 0.35), rng)
        _part(p, 0, 0, 0.0, 0.47 * h, 0.7 * l, 0.7 * w, legs)
        _part(p, 0, 0, 0.47 * h, 0.86 * h, l, w, body)
        _part(p, 0, 0, 0.86 * h, h, min(0.24, l), 0.22, np.array(SKIN) * rng.uniform(0.6, 1.1))
    elif kind == "barrier":
        l, w, h = rng.uniform(1.6, 2.2), 0.45, rng.uniform(0.9, 1.1)
        _part(p, 0, 0, 0.0, h, l, w, body, TEX_STRIPES)
    elif kind == "traffic_cone":
        l = w = 0.42
        h = rng.uniform(0.7, 0.8)
        _part(p, 0, 0, 0.0, 0.05, l, w, body * 0.5)
        _part(p, 0, 0, 0.05, h, 0.24, 0.24, body, TEX_STRIPES)
    else:  # pushable
        l, w, h = rng.uniform(0.55, 0.8), rng.uniform(0.55, 0.8), rng.uniform(0.9, 1.2)
        _part(p, 0, 0, 0.0, h, l, w, body)
    return l, w, h


def make_agent(kind: str, rng: np.random.Generator, origin, heading: float, speed: float, attribute: str) -> Agent:
    """One annotated object; ``origin`` scene-frame (x, y) at t = 0, ``heading`` rad, ``speed`` m/s."""
    size, parts = _shape(kind, rng, attribute)
    return Agent(
        kind=kind, raw=MATERIALS[kind].raw, origin=np.asarray(origin, dtype=np.float64), heading=float(heading),
        speed=float(speed), attribute=attribute, size=tuple(float(v) for v in size),
        part_center=np.array([q[0] for q in parts], dtype=np.float64),
        part_half=np.array([q[1] for q in parts], dtype=np.float64),
        part_color=np.array([np.asarray(q[2], dtype=np.float64) for q in parts], dtype=np.float32).clip(0, 1),
        part_texture=np.array([q[3] for q in parts], dtype=np.int8),
        reflectivity=MATERIALS[kind].reflectivity,
    )


def default_attribute(kind: str, moving: bool, rng: np.random.Generator) -> str:
    """nuScenes attribute name for an object of ``kind`` ('' for movable objects, which have none)."""
    if kind in VEHICLES:
        return "vehicle.moving" if moving else ("vehicle.parked" if rng.random() < 0.8 else "vehicle.stopped")
    if kind in CYCLES:
        return "cycle.with_rider" if moving or rng.random() < 0.3 else "cycle.without_rider"
    if kind == "pedestrian":
        return "pedestrian.moving" if moving else "pedestrian.standing"
    return ""
