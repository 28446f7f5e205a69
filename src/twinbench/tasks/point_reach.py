"""`point-reach` (`twinbench/PointReach-v0`): a cheap 2D debug task for the evaluation machinery.

A point in the square workspace [-0.25, 0.25]^2 m must reach the goal disk (centre 0, radius 0.03 m)
and stay in it for `HOLD_STEPS` consecutive steps (success, the episode terminates). Action = absolute
target [x, y]; the point moves towards it by at most `MAX_STEP` m per step. 8 grid initial states on a
circle of radius 0.18 m; 60 steps per episode; 64x64 "pixels" drawn with numpy.
`fail_mode="nan"` (or `"raise"`) makes the simulation diverge at step `fail_step`, `"exit"` kills the
process there (as a crash in native code would), and `step_delay_s` emulates a costly simulator (tests).
"""

from __future__ import annotations

import os
import time

import gymnasium
import numpy as np
from gymnasium import spaces

from twinbench.errors import SimulationDiverged
from twinbench.tasks import register_task

HALF = 0.25  # workspace half-width, m
GOAL = np.zeros(2)
GOAL_RADIUS = 0.03
MAX_STEP = 0.02  # m per step
HOLD_STEPS = 5
N_GRID = 8
GRID_RADIUS = 0.18
EPISODE_STEPS = 60
IMG = 64


def grid_state(i: int) -> np.ndarray:
    """Initial position of grid state i: on a circle around the goal, 45 degrees apart."""
    a = 2 * np.pi * i / N_GRID
    return GOAL + GRID_RADIUS * np.array([np.cos(a), np.sin(a)])


class PointReachEnv(gymnasium.Env):
    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}
    task_description = task = "move the point into the yellow goal disk and hold it there"  # `task`: LeRobot

    def __init__(self, render_mode: str | None = "rgb_array", fail_mode: str | None = None,
                 fail_step: int = 5, step_delay_s: float = 0.0):
        if fail_mode not in (None, "nan", "raise", "exit"):
            raise ValueError(f"fail_mode must be None, 'nan', 'raise' or 'exit', got {fail_mode!r}")
        self.render_mode, self.fail_mode, self.fail_step = render_mode, fail_mode, int(fail_step)
        self.step_delay_s = float(step_delay_s)
        self._max_episode_steps = EPISODE_STEPS
        img = spaces.Box(0, 255, (IMG, IMG, 3), np.uint8)
        self.observation_space = spaces.Dict({
            "pixels": spaces.Dict({"front": img, "wrist": img}),
            "agent_pos": spaces.Box(-HALF, HALF, (2,), np.float32),
        })
        self.action_space = spaces.Box(-HALF, HALF, (2,), np.float32)
        c = (np.arange(IMG) + 0.5) / IMG * 2 * HALF - HALF  # pixel centres in metres
        self._px, self._py = np.meshgrid(c, -c)  # image row 0 = +y
        # the background with the translucent goal disk never changes: drawn once, copied per frame
        bg = np.full((IMG, IMG, 3), 200, np.uint8)
        goal = (self._px - GOAL[0]) ** 2 + (self._py - GOAL[1]) ** 2 < GOAL_RADIUS**2
        bg[goal] = (0.5 * bg[goal] + 0.5 * np.array([255, 220, 0])).astype(np.uint8)
        self._background = bg
        self._pos = grid_state(0)
        self._t = self._hold = 0

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        options = options or {}
        i = int(options.get("init_state", 0 if seed is None else int(seed) % N_GRID))  # tasks/__init__
        if i < 0:
            raise ValueError(f"options['init_state'] must be >= 0, got {i}")
        if options.get("sampled", False) or i >= N_GRID:
            while True:  # uniform in the workspace, at least 0.08 m from the goal
                p = self.np_random.uniform(-0.9 * HALF, 0.9 * HALF, 2)
                if np.linalg.norm(p - GOAL) > 0.08:
                    break
            self._pos = p
        else:
            self._pos = grid_state(i)
        self._t = self._hold = 0
        return self._obs(), {"is_success": False, "status": "ok"}

    def step(self, action):
        target = np.asarray(action, dtype=np.float64).reshape(2)
        d = target - self._pos
        n = np.linalg.norm(d)
        self._pos = np.clip(self._pos + (d if n <= MAX_STEP else d * MAX_STEP / n), -HALF, HALF)
        self._t += 1
        if self.step_delay_s > 0:
            time.sleep(self.step_delay_s)
        if self.fail_mode and self._t >= self.fail_step:
            if self.fail_mode == "raise":
                raise SimulationDiverged(reason=f"point_reach: forced divergence at step {self._t}")
            if self.fail_mode == "exit":
                os._exit(70)
            self._pos = np.full(2, np.nan)
        if not np.all(np.isfinite(self._pos)):
            why = f"point_reach: position {self._pos} is not finite"
            return self._obs(), 0.0, True, False, {"is_success": False, "status": "sim_error", "error": why}
        dist = float(np.linalg.norm(self._pos - GOAL))
        self._hold = self._hold + 1 if dist < GOAL_RADIUS else 0
        success = self._hold >= HOLD_STEPS
        reward = 1.0 - min(dist / HALF, 1.0)
        info = {"is_success": success, "status": "ok", "distance": dist}
        return self._obs(), reward, success, self._t >= EPISODE_STEPS, info

    def render(self):
        img = self._background.copy()
        if np.all(np.isfinite(self._pos)):
            agent = (self._px - self._pos[0]) ** 2 + (self._py - self._pos[1]) ** 2 < 0.012**2
            img[agent] = (220, 30, 30)
        return img

    def _obs(self):
        front = self.render()
        # wrist: a 32x32 window centred on the agent, upsampled x2 (edge-padded near the border)
        pos = np.nan_to_num(self._pos)
        col = int(np.clip((pos[0] + HALF) / (2 * HALF) * IMG, 0, IMG - 1))
        row = int(np.clip((HALF - pos[1]) / (2 * HALF) * IMG, 0, IMG - 1))
        pad = np.pad(front, ((16, 16), (16, 16), (0, 0)), mode="edge")
        wrist = pad[row:row + 32, col:col + 32].repeat(2, axis=0).repeat(2, axis=1)
        return {"pixels": {"front": front, "wrist": np.ascontiguousarray(wrist)},
                "agent_pos": self._pos.astype(np.float32)}


class PointReachExpert:
    """Scripted expert: commands the goal centre every step (straight line, rate-limited)."""

    def __init__(self, goal=GOAL):
        self.goal = np.asarray(goal, np.float32)

    def reset(self) -> None:
        pass

    def select_action(self, obs) -> np.ndarray:
        return self.goal.copy()


def make_expert(env) -> PointReachExpert:
    """The task's scripted expert (needs nothing from `env`: the goal is fixed)."""
    return PointReachExpert()


ENV_ID = "twinbench/PointReach-v0"
register_task("point-reach", env_id=ENV_ID, entry_point=f"{__name__}:PointReachEnv",
              make_expert=make_expert, n_grid_states=N_GRID, description=PointReachEnv.task_description,
              max_episode_steps=EPISODE_STEPS)
