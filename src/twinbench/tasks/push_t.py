"""`push-t` (`twinbench/PushT-v0`): push a rigid spring-mass T-block onto a goal pose (DESIGN §7).

The built-in workcell: procedural table and backdrop, the built-in xArm-7-like arm with a vertical
pusher held at a fixed height, and a T-block made of particles (volume lattice, springs within a radius,
max 50 neighbours, uniform Y = 3e4) with coloured surface Gaussians that follow its rigid motion.
State and action are the pusher tip's `[x, y]` (absolute target, metres, robot base frame).

Two named presets trade fidelity for speed (everything else is identical):
- `reference`: the reference twin, 5 mm particle lattice, 667 substeps per frame (dt = 5e-5 s);
- `fast`: a 15 mm lattice and 100 substeps per frame (dt = 3.3e-4 s), about 50x cheaper; used by the
  demo and the tests. Both are stiff, rigid-looking blocks; their pushes differ only through the
  coarser contact geometry.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import gymnasium
import numpy as np
from gymnasium import spaces

from twinbench.gaussians.cloud import GaussianCloud
from twinbench.physics import SimParams, SimulationDiverged
from twinbench.robot.builtin import load_builtin_arm
from twinbench.robot.controller import ControllerConfig
from twinbench.robot.gaussians import sample_robot_scan
from twinbench.robot.ik import solve_ik
from twinbench.scene.assets import backdrop_gaussians, mesh_surface_gaussians, table_gaussians
from twinbench.scene.cameras import front_camera, wrist_camera
from twinbench.scene.scene import ObjectSpec, Scene, ToolContact
from twinbench.tasks import register_task
from twinbench.tasks.push_t_geometry import (
    SuccessWindow,
    TBlockShape,
    grid_initial_states,
    mean_squared_distance,
    sample_block_particles,
    sample_initial_states,
)
from twinbench.transforms import planar_pose, transform_points
from twinbench.transforms import pose_matrix as ee_pose

ENV_ID = "twinbench/PushT-v0"
GOAL_RGBA = (1.0, 0.85, 0.1, 0.4)  # translucent yellow goal overlay


@dataclass(frozen=True)
class PushTConfig:
    """Every setting of the push-T twin. `PushTConfig.preset(name)` gives the named presets."""

    particle_spacing: float = 0.005  # m, T-block lattice
    spring_radius_factor: float = 1.9  # springs within this many lattice spacings
    substeps: int = 667  # per 30 Hz frame
    fps: float = 30.0
    episode_seconds: float = 60.0
    image_hw: tuple[int, int] = (240, 240)
    nominal_pose: tuple[float, float, float] = (0.5, 0.0, 0.0)  # x, y, theta of the T (grid centre)
    goal_pose: tuple[float, float, float] = (0.5, 0.0, 0.0)
    pusher_start: tuple[float, float] = (0.30, 0.0)
    pusher_height: float = 0.01  # m, pusher tip above the table
    workspace: tuple[float, float, float, float] = (0.2, 0.8, -0.3, 0.3)  # x_min, x_max, y_min, y_max
    ground_friction: float = 0.5
    pusher_friction: float = 0.3
    success_msd: float = 0.002  # m^2, mean squared particle distance to the goal
    success_window: int = 100
    success_min_hits: int = 30
    robot_gaussian_spacing: float = 0.006
    device: str = "cpu"

    @staticmethod
    def preset(name: str, **overrides) -> PushTConfig:
        """`reference` (default settings) or `fast` (coarse block, fewer substeps), plus overrides."""
        presets = {
            "reference": PushTConfig(),
            "fast": PushTConfig(particle_spacing=0.015, substeps=100),
        }
        if name not in presets:
            raise ValueError(f"push-t preset must be one of {sorted(presets)}, got {name!r}")
        return replace(presets[name], **overrides)

    @property
    def max_episode_steps(self) -> int:
        return int(round(self.episode_seconds * self.fps))


class PushTEnv(gymnasium.Env):
    """Gymnasium env over the push-T twin. See the module docstring and `twinbench.tasks` conventions."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 30}
    task_description = "push the T-shaped block onto the yellow target"

    def __init__(self, preset: str = "reference", render_mode: str | None = "rgb_array",
                 render_views: str = "front", **overrides):
        """`preset` names the twin's settings (`PushTConfig.preset`), `overrides` replace single fields;
        `render_views` is what `render()` returns: "front" (the default) or "front+wrist" side by side."""
        if render_views not in ("front", "front+wrist"):
            raise ValueError(f"render_views must be 'front' or 'front+wrist', got {render_views!r}")
        self.config = cfg = PushTConfig.preset(preset, **overrides)
        self.render_mode = render_mode
        self.render_views = render_views
        self.metadata = {**self.metadata, "render_fps": cfg.fps}
        self._max_episode_steps = cfg.max_episode_steps
        self.shape = TBlockShape()
        robot = load_builtin_arm("pusher")
        particles = sample_block_particles(self.shape, cfg.particle_spacing)
        block = ObjectSpec(
            "tblock", particles, mesh_surface_gaussians(self.shape.mesh(), (0.30, 0.42, 0.68)),
            rigid=True, spring_radius=cfg.spring_radius_factor * cfg.particle_spacing, max_neighbors=50,
        )
        sim = SimParams(
            dt=1.0 / cfg.fps / cfg.substeps, substeps=cfg.substeps, ground_restitution=0.0,
            ground_friction=cfg.ground_friction, object_collision=False,
            mesh_margin=0.6 * cfg.particle_spacing,
        )
        self.scene = Scene(
            robot,
            sample_robot_scan(robot, spacing=cfg.robot_gaussian_spacing),
            GaussianCloud.concatenate([table_gaussians(), backdrop_gaussians()]),
            [block],
            [front_camera(), wrist_camera("link7", offset=(0.0, -0.12, 0.05), look=(0.0, 0.0, 0.2))],
            sim=sim,
            controller=ControllerConfig(action_mode="planar", planar_height=cfg.pusher_height),
            tool_contact=ToolContact(restitution=0.0, friction=cfg.pusher_friction),
            image_hw=cfg.image_hw,
            device=cfg.device,
        )
        self.goal = planar_pose(*cfg.goal_pose)
        self._goal_particles = transform_points(self.goal, particles.astype(np.float64))
        self._goal_overlay = self._overlay_mask()
        # Coverage: centres of a 2 mm grid of cells over the T's footprint (block frame).
        lo = np.min([b[0] for b in self.shape.boxes()], axis=0)
        hi = np.max([b[1] for b in self.shape.boxes()], axis=0)
        gx, gy = np.meshgrid(np.arange(lo[0] + 0.001, hi[0], 0.002), np.arange(lo[1] + 0.001, hi[1], 0.002))
        cells = np.c_[gx.ravel(), gy.ravel(), np.full(gx.size, 0.5 * self.shape.height)]
        self._cover_local = cells[self.shape.contains(cells)]
        self._q_start = self._start_configuration()

        x0, x1, y0, y1 = cfg.workspace
        h, w = cfg.image_hw
        img = spaces.Box(0, 255, (h, w, 3), np.uint8)
        self.observation_space = spaces.Dict({
            "pixels": spaces.Dict({"front": img, "wrist": img}),
            "agent_pos": spaces.Box(np.array([x0, y0], np.float32), np.array([x1, y1], np.float32)),
        })
        self.action_space = spaces.Box(np.array([x0, y0], np.float32), np.array([x1, y1], np.float32))
        self._success = SuccessWindow(cfg.success_window, cfg.success_min_hits)
        self._steps = 0
        self._status = "ok"
        self._frames: dict[str, np.ndarray] = {}

    # ------------------------------------------------------------------ setup helpers
    def _start_configuration(self) -> np.ndarray:
        cfg = self.config
        ctrl = self.scene.controller.config
        target = ee_pose(np.array([*cfg.pusher_start, cfg.pusher_height]), np.asarray(ctrl.planar_quat))
        res = solve_ik(self.scene.robot, target, self.scene.robot.home_q)
        if not res.converged:
            raise RuntimeError(f"push-t: pusher start {cfg.pusher_start} is not reachable")
        return res.q

    def _overlay_mask(self) -> np.ndarray:
        """Pixels of the fixed camera image covered by the goal T (projected onto the table)."""
        from matplotlib.path import Path as PolyPath

        cam = self.scene.camera(self.scene.cameras[0])
        outline = transform_points(self.goal, np.c_[self.shape.outline_xy(), np.zeros(8)])
        p_cam = outline @ cam.world_to_cam[:3, :3].T + cam.world_to_cam[:3, 3]
        uv = np.c_[cam.fx * p_cam[:, 0] / p_cam[:, 2] + cam.cx, cam.fy * p_cam[:, 1] / p_cam[:, 2] + cam.cy]
        jj, ii = np.meshgrid(np.arange(cam.width) + 0.5, np.arange(cam.height) + 0.5)
        inside = PolyPath(uv).contains_points(np.c_[jj.ravel(), ii.ravel()])
        return inside.reshape(cam.height, cam.width)

    # ------------------------------------------------------------------ task quantities
    def initial_state(self, index: int | None, seed: int | None) -> np.ndarray:
        """(dx, dy, dtheta) of grid state `index`, or a sampled state when index is None."""
        if index is None:
            return sample_initial_states(1, seed=0 if seed is None else seed)[0]
        return grid_initial_states()[index]

    def block_pose(self) -> np.ndarray:
        """Current (x, y, theta) of the T-block (rigid fit of its particles)."""
        pose = self.scene.object_pose("tblock")
        return np.array([pose[0, 3], pose[1, 3], np.arctan2(pose[1, 0], pose[0, 0])])

    def goal_msd(self) -> float:
        """Mean squared distance (m^2) of the block's particles to their goal positions."""
        return mean_squared_distance(self.scene.particles("tblock"), self._goal_particles)

    def coverage(self) -> float:
        """Fraction of the goal T's footprint covered by the block (the dense reward)."""
        pose = self.scene.object_pose("tblock")
        world = transform_points(self.goal, self._cover_local)
        local = (world - pose[:3, 3]) @ pose[:3, :3]
        local[:, 2] = 0.5 * self.shape.height
        return float(np.mean(self.shape.contains(local, tol=1e-6)))

    # ------------------------------------------------------------------ gymnasium API
    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        options = dict(options or {})
        n_grid = len(grid_initial_states())
        index = int(options.get("init_state", 0))
        if index < 0:
            raise ValueError(f"options['init_state'] must be >= 0, got {index}")
        sampled = bool(options.get("sampled", False)) or index >= n_grid
        dx, dy, dth = self.initial_state(None if sampled else index, seed)
        x, y, th = self.config.nominal_pose
        self.scene.reset(self._q_start, {"tblock": planar_pose(x + dx, y + dy, th + dth)})
        self._success.reset()
        self._steps = 0
        self._status = "ok"
        obs = self._observe()
        return obs, {"is_success": False, "status": "ok", "msd": self.goal_msd()}

    def step(self, action):
        if self._status != "ok":
            raise RuntimeError("push-t: the episode ended with a simulation error; call reset()")
        a = np.asarray(action, dtype=np.float64)
        if a.shape != (2,):
            raise ValueError(f"action: expected shape (2,) = pusher [x, y] in metres, got {a.shape}")
        if not np.all(np.isfinite(a)):
            raise ValueError(f"action: contains NaN or inf: {a}")
        a = np.clip(a, self.action_space.low, self.action_space.high)
        self._steps += 1
        try:
            self.scene.step(a)
        except SimulationDiverged as err:
            self._status = "sim_error"
            info = {"is_success": False, "status": "sim_error", "error": str(err)}
            return self._last_obs, 0.0, True, False, info
        msd = self.goal_msd()
        success = self._success.update(msd < self.config.success_msd)
        obs = self._observe()
        truncated = self._steps >= self._max_episode_steps and not success
        info = {"is_success": success, "status": "ok", "msd": msd, "coverage": self.coverage()}
        return obs, info["coverage"], success, truncated, info

    def render(self):
        if self.render_views == "front+wrist":
            return np.concatenate([self._frames["front"], self._frames["wrist"]], axis=1)
        return self._frames["front"]

    def _observe(self) -> dict:
        outs = self.scene.render()
        frames = {name: out.rgb_uint8() for name, out in outs.items()}
        r, g, b, alpha = GOAL_RGBA
        m = self._goal_overlay  # blend only the goal's pixels
        blended = (1 - alpha) * frames["front"][m] + alpha * 255.0 * np.array([r, g, b], np.float32)
        frames["front"][m] = np.clip(blended + 0.5, 0, 255).astype(np.uint8)
        self._frames = frames
        self._last_obs = {
            "pixels": {"front": frames["front"], "wrist": frames["wrist"]},
            "agent_pos": self.scene.controller.ee_state().astype(np.float32),
        }
        return self._last_obs


def make_expert(env):
    from twinbench.tasks.push_t_expert import PushTExpert

    return PushTExpert(env)


if ENV_ID not in gymnasium.registry:
    gymnasium.register(id=ENV_ID, entry_point=PushTEnv)
register_task("push-t", env_id=ENV_ID, make_expert=make_expert, n_grid_states=16,
              description=PushTEnv.task_description)
