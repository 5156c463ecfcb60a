"""navapp: sparse-data liver deformation correction by linearized iterative boundary
reconstruction (LIBR; Heiselman & Miga, IEEE TMI 2020).

Sub-packages, in the one direction data flows:
anatomy -> mechanics -> simulation -> registration -> evaluation; ``app`` only calls them.
All lengths are millimetres unless a docstring says otherwise. The maths is restated in
``docs/design.md``; choices made where the paper is open are in ``docs/decisions/index.md``.

The public API (everything in ``__all__``; imported on first use, so ``import navapp`` is
cheap)::

    import navapp
    case = navapp.read_case("my-case")                 # case folder (docs/design.md §3)
    model, seconds = navapp.prepare(case)              # tet mesh, basis (k = 45), model
    reg = navapp.register(model, case.intraop)         # rigid ICP, then LIBR (eq. 7–13)
    moved = reg.transform(case.preop.liver.vertices)   # eq. 8 at any preoperative points
    # data already in the preoperative frame, right to within 1.5 mm and 1.5° per axis:
    reg = navapp.register(model, case.intraop, pose_prior=navapp.PosePrior(1.5, 1.5))
    x0, x1 = case.need_truth().tre_points(model.basis.nodes)  # a case with truth: where the nodes truly are

    scene = navapp.load_scene(navapp.scene_dir() / "phantom0-L.toml")
    navapp.simulate(scene, "phantom0-L")               # a simulated case folder with truth
"""

from importlib import import_module
from typing import TYPE_CHECKING

__version__ = "0.1.0"

# public name → the module that defines it (imported lazily, PEP 562)
_EXPORTS = {
    # case folders and the preoperative model
    "Case": "navapp.anatomy.caseio",
    "read_case": "navapp.anatomy.caseio",
    "write_case": "navapp.anatomy.caseio",
    "PreopModel": "navapp.anatomy.model",
    "make_phantom": "navapp.anatomy.phantom",
    # features and defaults
    "Feature": "navapp.features",
    "FEATURES": ("navapp.features", "TABLE"),
    "EDGE_MM": "navapp.defaults",
    "K": "navapp.defaults",
    # mechanics
    "Basis": "navapp.mechanics.basis",
    "BasisSettings": "navapp.mechanics.basis",
    "HeldSupports": "navapp.mechanics.supports",
    "case_supports": "navapp.mechanics.supports",
    # registration
    "prepare": "navapp.registration.pipeline",
    "register": "navapp.registration.pipeline",
    "rigid_starts": "navapp.registration.pipeline",
    "deform_points": "navapp.registration.pipeline",
    "write_outputs": "navapp.registration.pipeline",
    "tre_stats": "navapp.geometry.tre",
    "mean_tre": "navapp.geometry.tre",
    "TreStats": "navapp.geometry.tre",
    "Registration": "navapp.registration.pipeline",
    "RobustOptions": "navapp.registration.pipeline",
    "LocalModeOptions": "navapp.registration.local_modes",
    "PosePrior": "navapp.registration.prior",
    "declared_pose": "navapp.registration.prior",
    "RegistrationModel": "navapp.registration.model",
    "LMOptions": "navapp.registration.libr",
    "LibrResult": "navapp.registration.libr",
    "Weights": "navapp.registration.objective",
    "Correspondence": "navapp.registration.objective",
    "RigidResult": "navapp.registration.rigid",
    "FitQuality": "navapp.registration.quality",
    # simulation
    "Scene": "navapp.simulation.scene",
    "load_scene": "navapp.simulation.scene",
    "demo_scene": "navapp.simulation.scene",
    "scene_dir": "navapp.simulation.scene",
    "study_scenes": "navapp.simulation.scene",
    "simulate": "navapp.simulation.simulate",
    "data_level": "navapp.simulation.levels",
    # errors
    "NavappError": "navapp.errors",
    "InputError": "navapp.errors",
}

__all__ = [
    "Basis", "BasisSettings", "Case", "Correspondence", "EDGE_MM", "FEATURES", "Feature", "FitQuality",
    "HeldSupports", "InputError", "K", "LMOptions", "LibrResult", "LocalModeOptions", "NavappError", "PosePrior",
    "PreopModel", "Registration", "RegistrationModel", "RigidResult", "RobustOptions", "Scene", "TreStats",
    "Weights", "case_supports", "data_level", "declared_pose", "deform_points", "demo_scene", "load_scene",
    "make_phantom", "mean_tre", "prepare", "read_case", "register", "rigid_starts", "scene_dir", "simulate",
    "study_scenes", "tre_stats", "write_case", "write_outputs",
]  # the keys of _EXPORTS (a test checks)

if TYPE_CHECKING:  # what type checkers and editors see; at run time ``__getattr__`` imports on first use
    from .anatomy.caseio import Case, read_case, write_case
    from .anatomy.model import PreopModel
    from .anatomy.phantom import make_phantom
    from .defaults import EDGE_MM, K
    from .errors import InputError, NavappError
    from .features import TABLE as FEATURES
    from .features import Feature
    from .geometry.tre import TreStats, mean_tre, tre_stats
    from .mechanics.basis import Basis, BasisSettings
    from .mechanics.supports import HeldSupports, case_supports
    from .registration.libr import LibrResult, LMOptions
    from .registration.local_modes import LocalModeOptions
    from .registration.model import RegistrationModel
    from .registration.objective import Correspondence, Weights
    from .registration.pipeline import (
        Registration,
        RobustOptions,
        deform_points,
        prepare,
        register,
        rigid_starts,
        write_outputs,
    )
    from .registration.prior import PosePrior, declared_pose
    from .registration.quality import FitQuality
    from .registration.rigid import RigidResult
    from .simulation.levels import data_level
    from .simulation.scene import Scene, demo_scene, load_scene, scene_dir, study_scenes
    from .simulation.simulate import simulate


def __getattr__(name: str):
    target = _EXPORTS.get(name)
    if target is None:
        raise AttributeError(f"module 'navapp' has no attribute {name!r}")
    module, attr = target if isinstance(target, tuple) else (target, name)
    value = getattr(import_module(module), attr)
    globals()[name] = value  # later look-ups skip this function
    return value


def __dir__():
    return sorted(set(globals()) | set(__all__))
