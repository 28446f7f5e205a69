"""Adapter running a LeRobot (0.6) pretrained policy in a twinbench env. Only the observation mapping
(`lerobot_arrays`) is tested here; loading and running a policy is UNTESTED: lerobot is an optional
extra (`pip install 'twinbench[lerobot]'`) that this project's CI does not install.

Observation mapping (what LeRobot's `preprocess_observation` produces for gym envs):
`pixels[cam]` HxWx3 uint8 -> `observation.images.<cam>` float32 (1, 3, H, W) in [0, 1];
`agent_pos` -> `observation.state` float32 (1, D); plus `task` = [task description].
Per step: `preprocessor(obs)` -> `policy.select_action(obs)` (the policy keeps its own action queue
for chunked models) -> `postprocessor(action)` -> numpy (A,).
Loading follows lerobot's eval script: `PreTrainedConfig.from_pretrained(path)`,
`get_policy_class(cfg.type).from_pretrained(path, config=cfg)` and
`make_pre_post_processors(policy_cfg=cfg, pretrained_path=path, preprocessor_overrides=...)`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

EXTRA_HINT = "pip install 'twinbench[lerobot]'"


def _import_lerobot():
    try:
        import torch
        from lerobot.configs.policies import PreTrainedConfig
        try:  # lerobot 0.4-0.6 keep the factory module; newer ones also export from lerobot.policies
            from lerobot.policies.factory import get_policy_class, make_pre_post_processors
        except ImportError:
            from lerobot.policies import get_policy_class, make_pre_post_processors
    except ImportError as err:
        raise ImportError(f"lerobot: policies need the 'lerobot' extra ({EXTRA_HINT}); "
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
    out["task"] = [task_description]
    return out


def observation_to_lerobot(obs: dict, task_description: str, device: str = "cpu") -> dict:
    """`lerobot_arrays` as torch tensors on `device` (what a LeRobot preprocessor takes)."""
    import torch

    return {k: v if k == "task" else torch.from_numpy(np.ascontiguousarray(v)).to(device)
            for k, v in lerobot_arrays(obs, task_description).items()}


class LeRobotPolicy:
    """A LeRobot `pretrained_model` folder (config.json + model.safetensors + processor files)."""

    def __init__(self, path: str | Path, *, task_description: str = "", device: str = "cpu"):
        torch, PreTrainedConfig, get_policy_class, make_pre_post_processors = _import_lerobot()
        self.path = Path(path)
        if not (self.path / "config.json").is_file():
            raise ValueError(f"lerobot:{path}: no config.json there; give a LeRobot pretrained_model folder")
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
        self.n_action_steps = getattr(cfg, "n_action_steps", None)

    def reset(self) -> None:
        self.policy.reset()
        for proc in (self.preprocessor, self.postprocessor):
            if hasattr(proc, "reset"):
                proc.reset()

    def reseed(self, seed: int) -> None:
        self._torch.manual_seed(int(seed))
        self.reset()

    def select_action(self, obs: dict) -> np.ndarray:
        batch = self.preprocessor(observation_to_lerobot(obs, self.task_description, self.device))
        with self._torch.inference_mode():
            action = self.policy.select_action(batch)
        action = self.postprocessor(action)
        return action.detach().to("cpu").numpy().reshape(-1).astype(np.float32)
