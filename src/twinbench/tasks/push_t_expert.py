"""Scripted push-T expert: reads the true block and goal poses from the observation's
`environment_state` (privileged; the runner adds it for experts, or the env when made with
`environment_state=True`) and pushes the block onto the goal.

It plans with the twin's geometry: the block's outline (`ObjectSpec.outline`) and the pusher tip's radius
(`RobotSpec.tool_radius`), which `tasks.push_t.make_expert` reads from the env's twin. Each step it
scores candidate contacts on the outline: pushing at contact c (outward normal n)
along -n moves the block, to first order, with velocity -n and angular velocity -(r x n) / rho^2
(an isotropic limit-surface model, r = c - centroid, rho^2 = the footprint's mean squared radius). The
score is the predicted rate of change of the mean squared distance to the goal; the expert commits
to the best contact for a while, goes around the block to a point just outside it, then pushes
through it. Once the block is close enough it backs off and waits.
"""

from __future__ import annotations

import numpy as np

from twinbench.errors import PolicyError


def _wrap(a: float) -> float:
    return float((a + np.pi) % (2 * np.pi) - np.pi)


def _rot(th: float) -> np.ndarray:
    c, s = np.cos(th), np.sin(th)
    return np.array([[c, -s], [s, c]])


class PushTExpert:
    """Scripted expert for `twinbench/PushT-v0`: acts from `obs["agent_pos"]` and
    `obs["environment_state"]` = [x, y, theta, goal_x, goal_y, goal_theta, msd] (see tasks.push_t), for
    a block of footprint `outline` (a `twinbench.twin.shapes.Outline`) and a pusher tip of radius
    `pusher_radius` (m)."""

    uses_environment_state = True

    def __init__(self, outline, *, pusher_radius: float, contact_spacing: float = 0.01,
                 clearance: float = 0.012, push_depth: float = 0.015, commit_steps: int = 15,
                 done_msd: float = 0.0004):
        self.outline = outline
        self.pusher_radius = pusher_radius
        self.clearance = clearance
        self.push_depth = push_depth
        self.commit_steps = commit_steps
        self.done_msd = done_msd
        outline = outline.polygon
        pts, normals = [], []
        for i in range(len(outline)):
            a, b = outline[i], outline[(i + 1) % len(outline)]
            edge = b - a
            length = float(np.linalg.norm(edge))
            n = np.array([edge[1], -edge[0]]) / length  # outward for a counter-clockwise outline
            k = max(int(length / contact_spacing), 1)
            for t in (np.arange(k) + 0.5) / k:
                pts.append(a + t * edge)
                normals.append(n)
        pts, normals = np.array(pts), np.array(normals)
        approach = pts + normals * (self.pusher_radius + clearance)
        free = np.array([self._distance_to_t(p) > self.pusher_radius + 0.5 * clearance for p in approach])
        self._contacts, self._normals = pts[free], normals[free]
        self._rho2 = self.outline.polar_radius2()
        self._radius = float(np.max(np.linalg.norm(outline, axis=1)))
        self.reset()

    def _distance_to_t(self, p: np.ndarray) -> float:
        """Distance from a block-frame 2D point to the block (0 inside)."""
        return self.outline.distance(p)

    def reset(self) -> None:
        self._choice: int | None = None
        self._committed = 0

    def _scores(self, pose: np.ndarray, goal: np.ndarray) -> np.ndarray:
        """Predicted d(MSD)/dt per unit push speed for each candidate contact (lower is better)."""
        rot = _rot(pose[2])
        r = self._contacts @ rot.T
        n = self._normals @ rot.T
        vel = -n
        omega = -(r[:, 0] * n[:, 1] - r[:, 1] * n[:, 0]) / self._rho2
        dth = _wrap(pose[2] - goal[2])
        return 2.0 * vel @ (pose[:2] - goal[:2]) + 2.0 * np.sin(dth) * self._rho2 * omega

    def select_action(self, obs) -> np.ndarray:
        if "environment_state" not in obs:
            raise PolicyError("the push-T expert needs obs['environment_state'] (make the env with "
                              "environment_state=True, or let the evaluation runner add it)")
        pusher = np.asarray(obs["agent_pos"], dtype=np.float64)[:2]
        state = np.asarray(obs["environment_state"], dtype=np.float64)
        pose, goal, msd = state[0:3], state[3:6], float(state[6])
        rot = _rot(pose[2])
        if msd < self.done_msd:
            self._choice = None
            away = pusher - pose[:2]
            away /= max(np.linalg.norm(away), 1e-9)
            return (pose[:2] + away * (self._radius + 0.05)).astype(np.float32)

        scores = self._scores(pose, goal)
        if self._choice is None or self._committed >= self.commit_steps or scores[self._choice] >= 0:
            # Prefer strong contacts, lightly penalising the detour to reach them.
            offset = self._normals * (self.pusher_radius + self.clearance)
            approach = pose[:2] + (self._contacts + offset) @ rot.T
            travel = np.linalg.norm(approach - pusher, axis=1)
            self._choice = int(np.argmin(scores / self._radius + 0.02 * travel))
            self._committed = 0
        c = pose[:2] + rot @ self._contacts[self._choice]
        n = rot @ self._normals[self._choice]
        start = c + n * (self.pusher_radius + self.clearance)
        local_pusher = rot.T @ (pusher - pose[:2])
        touching = self._distance_to_t(local_pusher) < self.pusher_radius + 2 * self.clearance
        if np.linalg.norm(pusher - start) < 0.006 or (self._committed > 0 and touching):
            self._committed += 1
            return (c - n * self.push_depth).astype(np.float32)
        return self._travel(pusher, start, pose).astype(np.float32)

    def _travel(self, pusher: np.ndarray, target: np.ndarray, pose: np.ndarray) -> np.ndarray:
        """Next waypoint from the pusher to `target` that keeps clear of the block.

        Straight when the segment is clear; otherwise first back away from the block (along the distance
        gradient) until outside a circle that clears the whole T, then orbit towards the target's bearing.
        """
        rot = _rot(pose[2])
        to_local = lambda p: rot.T @ (p - pose[:2])  # noqa: E731
        safe = self.pusher_radius + 0.5 * self.clearance
        path = pusher + np.linspace(0, 1, 16)[:, None] * (target - pusher)
        path_clear = all(self._distance_to_t(to_local(p)) > safe for p in path)
        if path_clear:
            return target
        radius = self._radius + self.pusher_radius + self.clearance
        rel = pusher - pose[:2]
        if np.linalg.norm(rel) < radius - 0.005:
            local = to_local(pusher)
            away = local - self.outline.nearest(local)
            if np.linalg.norm(away) < 1e-9:
                away = local
            away = rot @ (away / max(np.linalg.norm(away), 1e-9))
            return pusher + 0.03 * away
        a_p = np.arctan2(rel[1], rel[0])
        a_t = np.arctan2(*(target - pose[:2])[::-1])
        a = a_p + np.clip(_wrap(a_t - a_p), -0.5, 0.5)
        return pose[:2] + radius * np.array([np.cos(a), np.sin(a)])
