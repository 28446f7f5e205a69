"""Policy protocol and the action-queue base class for chunked policies (ACT / DP / VLA style)."""

from __future__ import annotations

from collections import deque
from typing import Protocol, runtime_checkable

import numpy as np

from twinbench.errors import PolicyError


@runtime_checkable
class Policy(Protocol):
    """What the runner drives: `reset()` at the start of an episode, then one `select_action` per step.

    A policy with `uses_environment_state = True` (a scripted expert) is given the task's privileged
    `environment_state` vector in its observation (from the env's `info["privileged"]`); no other
    policy sees it.
    """

    def reset(self) -> None: ...

    def select_action(self, obs: dict) -> np.ndarray: ...


class ChunkedPolicy:
    """Base class for policies that predict a chunk of actions at once.

    Subclasses implement `predict_chunk(obs) -> (T, A)`; `select_action` executes the first
    `n_action_steps` actions of each chunk (all of it when None) before predicting again, each passed
    through `finish_action(action, obs)` with the observation of the step it is executed at (identity
    here; per-step action modes of `policies.io` convert there).
    """

    chunk_size: int | None = None
    n_action_steps: int | None = None

    def __init__(self, n_action_steps: int | None = None):
        if n_action_steps is not None and int(n_action_steps) < 1:
            raise ValueError(f"n_action_steps must be >= 1 or None, got {n_action_steps}")
        self.n_action_steps = None if n_action_steps is None else int(n_action_steps)
        self._queue: deque[np.ndarray] = deque()
        self.n_predictions = 0  # chunks predicted since construction (tests, diagnostics)

    def predict_chunk(self, obs: dict) -> np.ndarray:
        raise NotImplementedError

    def reset(self) -> None:
        self._queue.clear()

    def select_action(self, obs: dict) -> np.ndarray:
        if not self._queue:
            chunk = np.asarray(self.predict_chunk(obs))
            if chunk.ndim == 1:
                chunk = chunk[None]
            if chunk.ndim != 2 or len(chunk) == 0:
                raise PolicyError(f"{type(self).__name__}.predict_chunk returned shape {chunk.shape}; "
                                  "expected (T, action_dim) with T >= 1")
            self.chunk_size = len(chunk)
            self.n_predictions += 1
            n = len(chunk) if self.n_action_steps is None else min(self.n_action_steps, len(chunk))
            self._queue.extend(chunk[:n])
        return self.finish_action(self._queue.popleft(), obs)

    def finish_action(self, action: np.ndarray, obs: dict) -> np.ndarray:
        return action


class OpenLoopPolicy:
    """Plays back a fixed action sequence (T, A), one row per step; PolicyError past its end."""

    def __init__(self, actions: np.ndarray):
        self.actions, self._t = np.asarray(actions), 0

    def reset(self) -> None:
        self._t = 0

    def select_action(self, obs: dict) -> np.ndarray:
        if self._t >= len(self.actions):
            raise PolicyError(f"open-loop actions exhausted after {len(self.actions)} steps")
        self._t += 1
        return self.actions[self._t - 1]
