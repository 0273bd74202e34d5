"""MuJoCo quadrotor simulator: the stand-in for the real vehicle and motion-capture system.

The in-process API is :class:`QuadrotorSim`; effects that make it differ from the nominal
model are switched on with an effects file (:mod:`simulator.effects`).
"""

from simulator.effects import EFFECTS, Effects, ParamSpec, load_effects
from simulator.mocap import GyroConfig, GyroSample, MocapConfig, MocapSample
from simulator.quadrotor import QuadrotorSim

__all__ = [
    "EFFECTS",
    "Effects",
    "GyroConfig",
    "GyroSample",
    "MocapConfig",
    "MocapSample",
    "ParamSpec",
    "QuadrotorSim",
    "load_effects",
]
