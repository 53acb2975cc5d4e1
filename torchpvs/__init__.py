"""torchpvs — piecewise variable-strain (PVS) equilibrium of concentric tube robots in PyTorch.

Pipeline: scene -> sections -> bases/quadrature -> energy -> Newton solve -> outputs.
"""

from .scene import Actuation, Load, Scene, SceneError, Tube, builtin_scenes, load_scene
from .solver import SolverError, SolverOptions, solve
from .equilibrium import Equilibrium

__all__ = [
    "Tube", "Actuation", "Load", "Scene", "SceneError", "load_scene", "builtin_scenes",
    "SolverOptions", "SolverError", "solve", "Equilibrium",
]
__version__ = "0.1.0"
