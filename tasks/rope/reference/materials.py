"""Physical ropes, shared by the fine simulators (newton.py, and any other engine): one definition of a
rope's material and the named variants the correction campaign runs on.

The seven ropes span what is physically different, as the flying knot's seven real ropes did (7-25 mm
thick, 0.013-0.5 kg/m): stiffness (stiff, soft), mass and thickness (heavy, light), length (long), internal
damping (damped) and the mass distribution (heavy_end, a 50 g weight at the free end); `default` is the
built-in references' rope. `thick` (25 mm, 0.5 kg/m) and `thread` (4 mm, 0.013 kg/m) are the flying knot's extremes,
beyond the seven's span.
"""
from __future__ import annotations

from dataclasses import dataclass

from wrenorm.errors import InputError


@dataclass(frozen=True)
class RopeMaterial:
    length: float = 1.1  # m
    mass: float = 0.2  # kg, the rope itself (tip_mass comes on top)
    radius: float = 0.005  # m
    bend_stiffness: float = 3e-3  # EI, N m^2
    twist_stiffness: float = 2.3e-3  # GJ, N m^2 (GJ/EI = 1/(1+nu) for a solid isotropic section)
    bend_damping_time: float = 2e-3  # s: bend damping = EI/ds * this (internal friction of the braid)
    stretch_stiffness: float = 1e6  # N/m per joint: nearly inextensible at rope loads of a few N
    contact_stiffness: float = 2e4  # N/m (newton's penalty contact)
    contact_damping: float = 5.0  # N s/m
    friction: float = 0.3
    contact_timeconst: float = 1e-3  # s, a soft-constraint engine's contact time constant (MuJoCo's solref)
    contact_dampratio: float = 1.0
    tip_mass: float = 0.0  # kg: an extra point mass at the free end

    @property
    def linear_density(self) -> float:
        return self.mass / self.length


VARIANTS: dict[str, RopeMaterial] = {
    "default": RopeMaterial(),
    "stiff": RopeMaterial(bend_stiffness=1e-2, twist_stiffness=7.7e-3),
    "soft": RopeMaterial(bend_stiffness=1e-3, twist_stiffness=7.7e-4),
    "heavy": RopeMaterial(mass=0.4, radius=0.007),
    "light": RopeMaterial(mass=0.1, radius=0.0035, bend_stiffness=1e-3, twist_stiffness=7.7e-4),
    "long": RopeMaterial(length=1.4, mass=0.2 * 1.4 / 1.1),
    "damped": RopeMaterial(bend_damping_time=2e-2),
    "heavy_end": RopeMaterial(tip_mass=0.05),
    # the flying knot's extremes, outside the seven (never part of a campaign or of any choice of the loop)
    "thick": RopeMaterial(mass=0.55, radius=0.0125, bend_stiffness=3e-2, twist_stiffness=2.3e-2),
    "thread": RopeMaterial(mass=0.0143, radius=0.002, bend_stiffness=1e-4, twist_stiffness=7.7e-5),
}


def get_variant(name: str, source: str = "--variant") -> RopeMaterial:
    if name not in VARIANTS:
        raise InputError(source, "variant", f"unknown rope variant {name!r}; choose one of {sorted(VARIANTS)}")
    return VARIANTS[name]
