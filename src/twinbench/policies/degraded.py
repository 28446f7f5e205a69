"""Degraded experts: a family of "checkpoints" of known, decreasing quality for testing the pipeline.

`DegradedPolicy(base, level, seed)` perturbs every action of `base`:
- Gaussian noise with standard deviation `level * NOISE_SCALE * half_range` (half-range of the action
  space, per dimension);
- with probability `level * GLITCH_PROB` per step, a glitch: half the time the previous executed action
  is repeated (stale), otherwise a uniformly random action in the action space is sent.
Actions are clipped to the action space. Level 0 is the unmodified expert.

Train-step mapping (for per-checkpoint curves): `train_step = round((1 - level) * FULL_TRAINING_STEPS)`,
FULL_TRAINING_STEPS = 100_000, so `expert@0.3` is "step_70000" and better checkpoints have larger steps.
"""

from __future__ import annotations

import numpy as np

NOISE_SCALE = 1.0
GLITCH_PROB = 0.5
FULL_TRAINING_STEPS = 100_000


def level_to_train_step(level: float) -> int:
    """The documented mapping level -> train_step (level 0 = fully trained)."""
    if not 0.0 <= level <= 1.0:
        raise ValueError(f"degradation level must be in [0, 1], got {level}")
    return int(round((1.0 - level) * FULL_TRAINING_STEPS))


class DegradedPolicy:
    """`base` with action noise and glitches proportional to `level` in [0, 1]; deterministic per seed."""

    def __init__(self, base, level: float, seed: int, low, high):
        level_to_train_step(level)  # validates the level
        self.base, self.level, self.seed = base, float(level), int(seed)
        self.low, self.high = np.asarray(low, np.float64), np.asarray(high, np.float64)
        if (self.low.shape != self.high.shape or np.any(self.low > self.high)
                or not np.all(np.isfinite(self.low)) or not np.all(np.isfinite(self.high))):
            raise ValueError(f"DegradedPolicy: action bounds must be finite with low <= high (the noise "
                             f"scales with the range), got low={self.low}, high={self.high}")
        self._half = 0.5 * (self.high - self.low)  # half-range of the action space, per dimension
        self.reset()

    @property
    def uses_environment_state(self) -> bool:
        """Whether the wrapped policy reads the privileged `environment_state` (scripted experts)."""
        return bool(getattr(self.base, "uses_environment_state", False))

    def reset(self) -> None:
        self.base.reset()
        self._rng = np.random.default_rng(self.seed)
        self._prev: np.ndarray | None = None

    def reseed(self, seed: int) -> None:
        """Use `seed` for the following episodes (the runner gives every episode its own seed)."""
        self.seed = int(seed)
        self.reset()

    def select_action(self, obs: dict) -> np.ndarray:
        a = np.asarray(self.base.select_action(obs), np.float64)
        a = a + self._rng.normal(0.0, 1.0, a.shape) * self.level * NOISE_SCALE * self._half
        if self._rng.random() < self.level * GLITCH_PROB:
            if self._prev is not None and self._rng.random() < 0.5:
                a = self._prev
            else:
                a = self._rng.uniform(self.low, self.high)
        a = np.clip(a, self.low, self.high)
        self._prev = a
        return a.astype(np.float32)
