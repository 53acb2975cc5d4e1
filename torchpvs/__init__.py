"""torchpvs — piecewise variable-strain (PVS) equilibrium of concentric tube robots in PyTorch.

Pipeline: scene -> sections -> bases/quadrature -> energy -> plan + Newton kernel -> implicit
backward -> outputs (docs/index.md maps each stage to its module).
"""

from .calibration import Calibration, calibrate
from .continuation import ActuationPath, Continuation, FoldEvent, continuation
from .equilibrium import Equilibrium
from .force_control import ForceControlled, solve_force_controlled
from .implicit import NearSingularStiffnessWarning
from .inverse_kinematics import IKResult, inverse_kinematics
from .layer import CTR
from .options import AccuracyWarning, SolverError, SolverOptions
from .plan import Plan
from .scene import Actuation, Load, Scene, SceneError, Tube, builtin_scenes, load_scene
from .solver import solve
from .tracker import Tracker, TrackState

__all__ = [
    "Tube", "Actuation", "Load", "Scene", "SceneError", "load_scene", "builtin_scenes",
    "SolverOptions", "SolverError", "AccuracyWarning", "Plan", "solve", "Equilibrium", "CTR",
    "NearSingularStiffnessWarning",
    "continuation", "ActuationPath", "Continuation", "FoldEvent",
    "solve_force_controlled", "ForceControlled", "inverse_kinematics", "IKResult",
    "calibrate", "Calibration", "Tracker", "TrackState",
]
__version__ = "0.1.0"
