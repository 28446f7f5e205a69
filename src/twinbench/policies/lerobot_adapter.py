"""Adapter running a LeRobot (0.6) pretrained policy in a twinbench env (extra `lerobot`, Python >= 3.12).

Observation mapping (what LeRobot's `preprocess_observation` produces for gym envs), after the policy's
`policies.io` observation map (default preset `lerobot`: cameras under their own names, native size):
`pixels[cam]` HxWx3 uint8 -> `observation.images.<cam>` float32 (1, 3, H, W) in [0, 1];
`agent_pos` -> `observation.state` float32 (1, D); plus `task` = [task description].
Per step: `preprocessor(obs)` -> `policy.select_action(obs)` (the policy keeps its own action queue
for chunked models) -> `postprocessor(action)` -> the io's action handling -> numpy (A,). With
`n_action_steps` (spec option or io) or chunk-relative actions, twinbench keeps the queue instead:
`predict_action_chunk` -> postprocessor -> io actions (the pose at the chunk's start) -> first N.
Loading follows lerobot's eval script: `PreTrainedConfig.from_pretrained(path)`,
`get_policy_class(cfg.type).from_pretrained(path, config=cfg)` and
`make_pre_post_processors(policy_cfg=cfg, pretrained_path=path, preprocessor_overrides=...)`.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from twinbench.policies.base import ChunkedPolicy

EXTRA_HINT = "pip install 'twinbench[lerobot]'"
PROCESSOR_FILES = ("policy_preprocessor.json", "policy_postprocessor.json")


def import_lerobot():
    """(torch, PreTrainedConfig, get_policy_class, make_pre_post_processors); ImportError naming the extra."""
    try:
        import torch
        from lerobot.configs.policies import PreTrainedConfig
        try:  # lerobot 0.4-0.6 keep the factory module; newer ones also export from lerobot.policies
            from lerobot.policies.factory import get_policy_class, make_pre_post_processors
        except ImportError:
            from lerobot.policies import get_policy_class, make_pre_post_processors
    except ImportError as err:
        need = "" if sys.version_info >= (3, 12) else " and Python >= 3.12 (LeRobot 0.6)"
        raise ImportError(f"lerobot: policies need the 'lerobot' extra ({EXTRA_HINT}){need}; "
                          f"import failed: {err}") from err
    return torch, PreTrainedConfig, get_policy_class, make_pre_post_processors


def lerobot_arrays(obs: dict, task_description: str) -> dict:
    """Our observation -> LeRobot's batched keys as numpy: images float32 (1, 3, H, W) in [0, 1],
    state float32 (1, D), task [description]."""
    out: dict = {}
    for cam, img in obs["pixels"].items():
        img = np.asarray(img)
        if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
            raise ValueError(f"pixels[{cam!r}] must be HxWx3 uint8, got {img.shape} {img.dtype}")
        out[f"observation.images.{cam}"] = (img.transpose(2, 0, 1)[None] / np.float32(255)).astype(np.float32)
    out["observation.state"] = np.asarray(obs["agent_pos"], np.float32).reshape(1, -1)
    if "environment_state" in obs:
        out["observation.environment_state"] = np.asarray(obs["environment_state"], np.float32).reshape(1, -1)
    out["task"] = [task_description]
    return out


def observation_to_lerobot(obs: dict, task_description: str, device: str = "cpu") -> dict:
    """`lerobot_arrays` as torch tensors on `device` (what a LeRobot preprocessor takes)."""
    import torch

    return {k: v if k == "task" else torch.from_numpy(np.ascontiguousarray(v)).to(device)
            for k, v in lerobot_arrays(obs, task_description).items()}


def check_checkpoint(path: Path) -> None:
    """A clear error for a folder that LeRobot cannot load as a policy with its processors."""
    if not (path / "config.json").is_file():
        raise ValueError(f"lerobot:{path}: no config.json there; give a LeRobot pretrained_model folder")
    missing = [f for f in PROCESSOR_FILES if not (path / f).is_file()]
    if missing:
        raise ValueError(
            f"lerobot:{path}: {', '.join(missing)} missing (policy.save_pretrained alone writes only the "
            "weights and config). Save the processors next to them: `pre, post = make_pre_post_processors("
            "policy.config, dataset_stats=stats)`, then `pre.save_pretrained(PATH)` and "
            "`post.save_pretrained(PATH)`; lerobot-train's checkpoints/*/pretrained_model folders have them")


class LeRobotPolicy(ChunkedPolicy):
    """A LeRobot `pretrained_model` folder (config.json + model.safetensors + processor files).

    `io`: a `policies.io` preset name / JSON file / PolicyIO (default `lerobot`); `n_action_steps`
    overrides the io's."""

    def __init__(self, path: str | Path, *, task_description: str = "", device: str = "cpu", io=None,
                 n_action_steps: int | None = None):
        from twinbench.policies.io import load_policy_io

        torch, PreTrainedConfig, get_policy_class, make_pre_post_processors = import_lerobot()
        self.path = Path(path)
        check_checkpoint(self.path)
        self.io = load_policy_io(io).with_n_action_steps(n_action_steps)
        super().__init__(self.io.action.n_action_steps)
        self._torch, self.device, self.task_description = torch, device, task_description
        cfg = PreTrainedConfig.from_pretrained(str(self.path))
        cfg.pretrained_path = str(self.path)
        cfg.device = device
        self.policy = get_policy_class(cfg.type).from_pretrained(str(self.path), config=cfg)
        self.policy.eval()
        self.preprocessor, self.postprocessor = make_pre_post_processors(
            policy_cfg=cfg, pretrained_path=str(self.path),
            preprocessor_overrides={"device_processor": {"device": device}},
        )
        self.chunk_size = getattr(cfg, "chunk_size", None)
        # twinbench's queue when the executed steps or the chunk's reference pose matter, else LeRobot's own
        self.own_queue = self.n_action_steps is not None or self.io.action.mode == "chunk_relative"
        if not self.own_queue:
            self.n_action_steps = getattr(cfg, "n_action_steps", None)

    def reset(self) -> None:
        super().reset()
        self.policy.reset()
        for proc in (self.preprocessor, self.postprocessor):
            if hasattr(proc, "reset"):
                proc.reset()

    def reseed(self, seed: int) -> None:
        self._torch.manual_seed(int(seed))
        self.reset()

    def _batch(self, obs: dict) -> dict:
        mapped = self.io.request(obs, self.task_description)
        return self.preprocessor(observation_to_lerobot(mapped, self.task_description, self.device))

    def predict_chunk(self, obs: dict) -> np.ndarray:
        with self._torch.inference_mode():
            chunk = self.policy.predict_action_chunk(self._batch(obs))
        chunk = self.postprocessor(chunk).detach().to("cpu").numpy()
        return self.io.actions(chunk.reshape(-1, chunk.shape[-1]), obs)

    def select_action(self, obs: dict) -> np.ndarray:
        if self.own_queue:
            return super().select_action(obs)
        with self._torch.inference_mode():
            action = self.policy.select_action(self._batch(obs))
        action = self.postprocessor(action).detach().to("cpu").numpy().reshape(1, -1)
        return self.io.step(self.io.actions(action, obs)[0], obs)

    def finish_action(self, action: np.ndarray, obs: dict) -> np.ndarray:
        return self.io.step(action, obs)
