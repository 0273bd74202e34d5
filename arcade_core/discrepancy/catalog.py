"""The library of candidate physical effects (design §6, step 3): names, units, ranges.

Plain data, no JAX: every effect has a canonical name, the system it belongs to, a
one-line physical description, its parameters (unit, plausible range, default, shape) and
the state components it acts on. The JAX model terms live in
:mod:`arcade_core.discrepancy.quadrotor` and :mod:`arcade_core.discrepancy.cartpole`, the
MuJoCo implementations in ``simulator.effects`` (which reads its parameter table from here,
so the two never disagree).

Frames and units as in design §4: world ENU, body FLU, SI. ``v_rel = v - wind`` is the
air-relative velocity, ``v_b = R^T v_rel`` its body-frame coordinates, ``m`` the vehicle
mass of the nominal model (airframe + electromagnet) and ``T`` the collective thrust.
"""

from __future__ import annotations

from types import MappingProxyType
from typing import NamedTuple


class ParamSpec(NamedTuple):
    """One effect parameter: unit, plausible range (per element), default and meaning.

    ``shape`` is ``()`` for a scalar or ``(3,)`` for a vector. ``default`` ``None`` means
    the parameter must be given.
    """

    unit: str
    low: float
    high: float
    default: float | tuple[float, ...] | None
    shape: tuple[int, ...]
    description: str


class EffectSpec(NamedTuple):
    """A candidate physical effect.

    ``acts_on`` lists the state components whose one-step prediction the effect changes
    directly (design §5 column names); the workflow measures the gap it closes there.
    """

    name: str
    system: str
    description: str
    params: MappingProxyType
    acts_on: tuple[str, ...]


_V = ("vx", "vy", "vz")
_W = ("wx", "wy", "wz")


def _spec(name, system, description, acts_on, **params: ParamSpec) -> EffectSpec:
    return EffectSpec(name, system, description, MappingProxyType(params), acts_on)


# fmt: off
#: Quadrotor effects (canonical names; the simulator implements exactly these).
QUADROTOR_EFFECTS: MappingProxyType = MappingProxyType({e.name: e for e in (
    _spec("rotor_drag", "quadrotor",
          "linear rotor (blade-flapping / induced) drag per body axis, "
          "F_body = -m diag(d) R^T (v - wind)", _V,
          d=ParamSpec("1/s", 0.0, 2.0, None, (3,),
                      "linear drag acceleration coefficients along body x, y, z; "
                      "F_body = -m diag(d) R^T (v - wind)")),
    _spec("quadratic_drag", "quadrotor",
          "bluff-body drag per body axis, F_body,i = -c_i |v_b,i| v_b,i", _V,
          c=ParamSpec("kg/m", 0.0, 0.2, None, (3,),
                      "quadratic drag coefficients along body x, y, z; "
                      "F_body,i = -c_i |v_b,i| v_b,i")),
    _spec("ground_effect", "quadrotor",
          "Cheeseman-Bennett thrust gain near the floor, T_IGE/T_OGE = 1/(1 - (R/4h)^2)", _V,
          rotor_radius_m=ParamSpec("m", 0.01, 0.2, 0.0381, (),
                                   "rotor radius R in the Cheeseman-Bennett gain "
                                   "1 / (1 - (R / 4h)^2); default 3-inch propeller")),
    _spec("thrust_scale", "quadrotor",
          "thrust-coefficient (or mass) mismatch: the rotors make scale x the nominal thrust",
          _V + _W,
          scale=ParamSpec("1", 0.5, 1.5, None, (),
                          "actual / nominal rotor thrust coefficient")),
    _spec("motor_lag", "quadrotor",
          "first-order motor (thrust) lag with another time constant than the vehicle file's",
          _V + _W,
          time_constant_s=ParamSpec("s", 0.002, 0.2, None, (),
                                    "first-order motor thrust time constant "
                                    "(replaces the vehicle file's value)")),
    _spec("rate_lag", "quadrotor",
          "extra lag of the body-rate loop: transport delay and first-order filter on the "
          "rate setpoints", _W,
          delay_s=ParamSpec("s", 0.0, 0.1, 0.0, (),
                            "transport delay of the body-rate setpoints before the "
                            "rate controller"),
          time_constant_s=ParamSpec("s", 0.0, 0.3, 0.0, (),
                                    "first-order filter on the body-rate setpoints "
                                    "before the rate controller")),
    _spec("com_offset", "quadrotor",
          "centre-of-mass offset: thrust makes a torque that the rate loop's integrator "
          "has to cancel", _W,
          offset_m=ParamSpec("m", -0.03, 0.03, None, (3,),
                             "airframe centre-of-mass offset from the geometric centre, "
                             "body FLU")),
    _spec("wind", "quadrotor",
          "constant wind; acts through the drag terms as an offset of the air velocity", _V,
          velocity_mps=ParamSpec("m/s", -15.0, 15.0, None, (3,),
                                 "constant wind velocity, world ENU; acts through the "
                                 "drag effects")),
)})

#: Cartpole effects, relative to the Appendix D nominal model.
CARTPOLE_EFFECTS: MappingProxyType = MappingProxyType({e.name: e for e in (
    _spec("cart_viscous_friction", "cartpole",
          "viscous friction on the cart, force -mu_c xdot", ("xdot", "thetadot"),
          mu_c=ParamSpec("N s/m", 0.0, 2.0, None, (), "cart viscous friction coefficient")),
    _spec("pole_viscous_friction", "cartpole",
          "viscous friction in the pole hinge, torque -mu_p thetadot", ("xdot", "thetadot"),
          mu_p=ParamSpec("N m s/rad", 0.0, 0.5, None, (),
                         "pole hinge viscous friction coefficient")),
    _spec("coulomb_friction", "cartpole",
          "dry (Coulomb) friction on the cart, force -F_c sign(xdot)", ("xdot", "thetadot"),
          force_n=ParamSpec("N", 0.0, 3.0, None, (),
                            "Coulomb friction force magnitude (sign smoothed over "
                            "0.01 m/s)")),
    _spec("force_bias", "cartpole",
          "constant additive force on the cart (mean of the force disturbance)",
          ("xdot", "thetadot"),
          mean_n=ParamSpec("N", -3.0, 3.0, None, (), "constant force bias"),
          std_n=ParamSpec("N", 0.0, 3.0, 0.0, (),
                          "standard deviation of the random force drawn every step "
                          "(simulation only; process noise, not part of the model)")),
    _spec("mass_mismatch", "cartpole",
          "cart and pole masses differ from the model's", ("xdot", "thetadot"),
          cart_mass_kg=ParamSpec("kg", 0.1, 10.0, None, (), "actual cart mass M"),
          pole_mass_kg=ParamSpec("kg", 0.01, 2.0, None, (), "actual pole mass m")),
    _spec("length_mismatch", "cartpole",
          "pole length differs from the model's", ("xdot", "thetadot"),
          pole_length_m=ParamSpec("m", 0.1, 5.0, None, (), "actual pole length L")),
)})
# fmt: on

#: Every effect by canonical name.
EFFECTS: MappingProxyType = MappingProxyType({**QUADROTOR_EFFECTS, **CARTPOLE_EFFECTS})
SYSTEMS = ("quadrotor", "cartpole")


def effects_for(system: str) -> MappingProxyType:
    """The effects of ``system`` (``"quadrotor"`` or ``"cartpole"``) by name."""
    if system == "quadrotor":
        return QUADROTOR_EFFECTS
    if system == "cartpole":
        return CARTPOLE_EFFECTS
    raise ValueError(f"unknown system {system!r}; known: {', '.join(SYSTEMS)}")


def describe(system: str | None = None) -> list[dict]:
    """JSON-ready listing (``arcade effects --json``): name, system, description, acts_on
    and parameters with unit, plausible range, default and meaning."""
    specs = EFFECTS.values() if system is None else effects_for(system).values()
    out = []
    for e in specs:
        params = {
            k: {
                "unit": p.unit,
                "range": [p.low, p.high],
                "default": p.default,
                "shape": list(p.shape),
                "description": p.description,
            }
            for k, p in e.params.items()
        }
        out.append(
            {
                "name": e.name,
                "system": e.system,
                "description": e.description,
                "acts_on": list(e.acts_on),
                "params": params,
            }
        )
    return out
