"""twinbench.twin: a twin is data (TwinSpec, on disk a twin directory), built once into a Twin + TwinState.

from twinbench.twin import build_twin, load_twin, save_twin
from twinbench.twin.cells import push_t_cell

spec = push_t_cell("fast")            # or load_twin("path/to/twin_dir")
save_twin(spec, "my_twin")            # twin.json + .ply + .npz (+ meshes, URDF)
twin, state = build_twin(spec, device="cpu")
twin.step(state, action); frames = twin.render(state)
"""

from twinbench.twin.build import Twin, TwinState, build_twin
from twinbench.twin.files import TwinFormatError, load_object, load_twin, save_object, save_twin
from twinbench.twin.spec import (
    CameraSpec,
    ColliderSpec,
    ColorMap,
    ContactSpec,
    ObjectSpec,
    RobotSpec,
    TwinSpec,
)

__all__ = [
    "CameraSpec",
    "ColliderSpec",
    "ColorMap",
    "ContactSpec",
    "ObjectSpec",
    "RobotSpec",
    "Twin",
    "TwinFormatError",
    "TwinSpec",
    "TwinState",
    "build_twin",
    "load_object",
    "load_twin",
    "save_object",
    "save_twin",
]
