"""Policy I/O as the policy was trained: what a policy is sent and how its reply becomes env actions.

    io = load_policy_io("openpi-libero")     # a preset name, or a JSON mapping file (same fields)
    request = io.request(obs, prompt)         # env observation -> the policy's input dict
    actions = io.actions(chunk, obs)          # the policy's (T, A) actions -> (T, env action)

A `lerobot:` or `remote:` policy spec picks one with `?io=NAME_OR_FILE` (see `policies.spec`).

Observation (`ObservationMap`; JSON keys in brackets):
- `layout` ["layout"]: "lerobot" = `{"pixels": {name: image}, "agent_pos": state, "prompt": text}` (the
  nested keys LeRobot's gym envs give; other observation entries pass through) or "flat" =
  `{key: image, ..., key: state, prompt_key: text}` and nothing else (openpi).
- `images` ["images"]: {name or key: camera}; None = every camera under its own name. Each image (HxWx3
  uint8) is cropped to `crop[camera]` = [top, left, height, width] pixels, rotated by 180 degrees for
  cameras in `flip`, then brought to `image_size` = [H, W] by `resize`: "pad" (aspect ratio kept, centred
  on zeros; openpi's `resize_with_pad`), "stretch", or "crop" (centre crop to the aspect, then resize).
- `state` ["state"]: {key: [part, ...]}, the parts concatenated (float32). Parts read `agent_pos`, whose
  layout is the env's: [x, y, z, qw, qx, qy, qz, gripper] (absolute / relative action modes; gripper
  1 = closed) or [x, y] (planar): "agent_pos" (all), "ee_pos" (3), "ee_quat_wxyz" (4), "ee_quat_xyzw"
  (4), "ee_axis_angle" (3), "gripper" (1), "gripper_fingers" (2: [+w/2, -w/2] with the opening
  w = 0.08 m * (1 - gripper), a LIBERO-style finger qpos derived from the command), "xy" (2),
  "zeros:N"; any other name is read from the observation itself (e.g. "joint_position").
- `prompt_key` ["prompt"]: key of the task text (None: not sent).

Actions (`ActionMap`, JSON object "actions"):
- `key` (reply entry, "actions"), `n_action_steps` (actions executed per chunk; None = all or, for
  `lerobot:` policies, the policy's own), `dims` (keep the first `dims` entries: models that pad),
- `scale` (per-entry multiplier applied first), `gripper` = [lo, hi] (the policy's gripper range, mapped
  linearly to [0, 1], 1 = closed; the last entry),
- `mode`: "absolute" (the result is the env's action) or "chunk_relative": each action is
  [dp (3), dr, g] relative to the end-effector pose (p0, R0 / q0) observed when the chunk was predicted,
  executed as the absolute action [p0 + R0 dp, q0 * dq, g] (env in absolute action mode); `rotation`
  says how dr is written: "axis_angle" (3), "quat_wxyz" or "quat_xyzw" (4).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field, fields, replace
from pathlib import Path

import numpy as np

from twinbench.transforms import (
    matrix_to_quat,
    matrix_to_rotvec,
    quat_multiply,
    quat_to_matrix,
    rotvec_to_matrix,
)

FINGER_OPENING = 0.08  # m, full opening for the "gripper_fingers" state part
LAYOUTS = ("lerobot", "flat")
RESIZES = ("pad", "stretch", "crop")
MODES = ("absolute", "chunk_relative")
ROTATIONS = {"axis_angle": 3, "quat_wxyz": 4, "quat_xyzw": 4}


# ---------------------------------------------------------------- images
def _resize(img: np.ndarray, h: int, w: int) -> np.ndarray:
    from PIL import Image

    if img.shape[:2] == (h, w):
        return img
    return np.asarray(Image.fromarray(img).resize((w, h), resample=Image.BILINEAR))


def resize_image(img: np.ndarray, size: tuple[int, int], mode: str = "pad") -> np.ndarray:
    """HxWx3 uint8 -> size[0] x size[1] x 3 uint8 (modes as in the module docstring)."""
    h, w = int(size[0]), int(size[1])
    ih, iw = img.shape[:2]
    if (ih, iw) == (h, w):
        return img
    if mode == "stretch":
        return _resize(img, h, w)
    if mode == "crop":
        ratio = min(iw / w, ih / h)
        ch, cw = int(round(h * ratio)), int(round(w * ratio))
        top, left = (ih - ch) // 2, (iw - cw) // 2
        return _resize(np.ascontiguousarray(img[top:top + ch, left:left + cw]), h, w)
    ratio = max(iw / w, ih / h)  # "pad"
    rh, rw = int(ih / ratio), int(iw / ratio)
    out = np.zeros((h, w, 3), np.uint8)
    top, left = max(0, (h - rh) // 2), max(0, (w - rw) // 2)
    out[top:top + rh, left:left + rw] = _resize(img, rh, rw)
    return out


# ---------------------------------------------------------------- state
def _ee(agent_pos: np.ndarray, part: str) -> np.ndarray:
    if agent_pos.shape != (8,):
        raise ValueError(f"state part {part!r} needs agent_pos [x, y, z, qw, qx, qy, qz, gripper] (an env "
                         f"in absolute or relative action mode); this env's agent_pos has shape "
                         f"{agent_pos.shape}")
    return agent_pos


def state_part(obs: dict, part: str) -> np.ndarray:
    """One named state part (module docstring) of an env observation, float64."""
    a = np.asarray(obs["agent_pos"], np.float64).reshape(-1)
    if part == "agent_pos":
        return a
    if part == "xy":
        return a[:2]
    if part.startswith("zeros:"):
        return np.zeros(int(part.split(":", 1)[1]))
    if part == "ee_pos":
        return _ee(a, part)[:3]
    if part == "ee_quat_wxyz":
        return _ee(a, part)[3:7]
    if part == "ee_quat_xyzw":
        return _ee(a, part)[[4, 5, 6, 3]]
    if part == "ee_axis_angle":
        return matrix_to_rotvec(quat_to_matrix(_ee(a, part)[3:7]))
    if part == "gripper":
        return _ee(a, part)[7:8]
    if part == "gripper_fingers":
        half = 0.5 * FINGER_OPENING * (1.0 - float(np.clip(_ee(a, part)[7], 0.0, 1.0)))
        return np.array([half, -half])
    if part in obs:
        return np.asarray(obs[part], np.float64).reshape(-1)
    raise ValueError(f"state part {part!r}: not a known part and not in the observation (keys "
                     f"{sorted(obs)}); known parts: agent_pos, xy, ee_pos, ee_quat_wxyz, ee_quat_xyzw, "
                     f"ee_axis_angle, gripper, gripper_fingers, zeros:N")


# ---------------------------------------------------------------- maps
@dataclass(frozen=True)
class ObservationMap:
    layout: str = "lerobot"
    images: dict[str, str] | None = None
    image_size: tuple[int, int] | None = None
    resize: str = "pad"
    crop: dict[str, tuple[int, int, int, int]] = field(default_factory=dict)
    flip: tuple[str, ...] = ()
    state: dict[str, tuple[str, ...]] = field(default_factory=lambda: {"agent_pos": ("agent_pos",)})
    prompt_key: str | None = "prompt"

    def __post_init__(self) -> None:
        if self.layout not in LAYOUTS:
            raise ValueError(f"layout: expected one of {LAYOUTS}, got {self.layout!r}")
        if self.resize not in RESIZES:
            raise ValueError(f"resize: expected one of {RESIZES}, got {self.resize!r}")
        if self.image_size is not None and (len(self.image_size) != 2 or min(self.image_size) < 1):
            raise ValueError(f"image_size: expected [height, width] >= 1, got {self.image_size}")
        for cam, box in self.crop.items():
            if len(box) != 4 or box[2] < 1 or box[3] < 1 or box[0] < 0 or box[1] < 0:
                raise ValueError(f"crop[{cam!r}]: expected [top, left, height, width], got {box}")

    def image(self, obs: dict, camera: str) -> np.ndarray:
        pixels = obs["pixels"]
        if camera not in pixels:
            raise ValueError(f"images: camera {camera!r} is not in the observation "
                             f"(cameras {sorted(pixels)})")
        img = np.asarray(pixels[camera])
        if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
            raise ValueError(f"pixels[{camera!r}] must be HxWx3 uint8, got {img.shape} {img.dtype}")
        if camera in self.crop:
            top, left, h, w = (int(v) for v in self.crop[camera])
            if top + h > img.shape[0] or left + w > img.shape[1]:
                raise ValueError(f"crop[{camera!r}] = {self.crop[camera]} exceeds the {img.shape[:2]} image")
            img = img[top:top + h, left:left + w]
        if camera in self.flip:
            img = img[::-1, ::-1]
        img = np.ascontiguousarray(img)
        return img if self.image_size is None else resize_image(img, self.image_size, self.resize)

    def request(self, obs: dict, prompt: str | None) -> dict:
        images = self.images if self.images is not None else {c: c for c in obs["pixels"]}
        imgs = {key: self.image(obs, cam) for key, cam in images.items()}
        states = {key: np.concatenate([state_part(obs, p) for p in parts]).astype(np.float32)
                  for key, parts in self.state.items()}
        if self.layout == "lerobot":  # other observation entries (depth, environment_state) pass through
            out: dict = {**{k: v for k, v in obs.items() if k != "pixels"}, "pixels": imgs, **states}
        else:
            out = {**imgs, **states}
        if self.prompt_key is not None and prompt is not None:
            out[self.prompt_key] = prompt
        return out


@dataclass(frozen=True)
class ActionMap:
    key: str = "actions"
    n_action_steps: int | None = None
    dims: int | None = None
    scale: tuple[float, ...] | None = None
    gripper: tuple[float, float] | None = None
    mode: str = "absolute"
    rotation: str = "axis_angle"

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ValueError(f"actions.mode: expected one of {MODES}, got {self.mode!r}")
        if self.rotation not in ROTATIONS:
            raise ValueError(f"actions.rotation: expected one of {sorted(ROTATIONS)}, got {self.rotation!r}")
        if self.n_action_steps is not None and int(self.n_action_steps) < 1:
            raise ValueError(f"actions.n_action_steps: must be >= 1 or null, got {self.n_action_steps}")
        if self.gripper is not None and (len(self.gripper) != 2 or self.gripper[0] == self.gripper[1]):
            raise ValueError(f"actions.gripper: expected [lo, hi] with lo != hi, got {self.gripper}")

    def actions(self, chunk, obs: dict) -> np.ndarray:
        a = np.asarray(chunk, np.float64)
        a = a[None] if a.ndim == 1 else a
        if a.ndim != 2 or len(a) == 0:
            raise ValueError(f"actions: expected a (T, A) chunk, got shape {a.shape}")
        if self.dims is not None:
            if a.shape[1] < self.dims:
                raise ValueError(f"actions.dims = {self.dims} but the policy's actions have "
                                 f"{a.shape[1]} entries")
            a = a[:, :self.dims]
        if self.scale is not None:
            if len(self.scale) != a.shape[1]:
                raise ValueError(f"actions.scale has {len(self.scale)} entries for {a.shape[1]}-d actions")
            a = a * np.asarray(self.scale)
        if self.gripper is not None:
            lo, hi = self.gripper
            a = a.copy()
            a[:, -1] = np.clip((a[:, -1] - lo) / (hi - lo), 0.0, 1.0)
        if self.mode == "chunk_relative":
            a = self._compose(a, np.asarray(obs["agent_pos"], np.float64).reshape(-1))
        return a.astype(np.float32)

    def _compose(self, a: np.ndarray, agent_pos: np.ndarray) -> np.ndarray:
        """[dp, dr, g] relative to the chunk's first pose -> absolute [p0 + R0 dp, q0 * dq, g]."""
        k = ROTATIONS[self.rotation]
        if a.shape[1] != 3 + k + 1:
            raise ValueError(f"chunk_relative actions with {self.rotation} rotations have {3 + k + 1} "
                             f"entries [dp, dr, gripper], got {a.shape[1]}")
        p0, q0 = _ee(agent_pos, "chunk_relative")[:3], agent_pos[3:7] / np.linalg.norm(agent_pos[3:7])
        r0 = quat_to_matrix(q0)
        dr = a[:, 3:3 + k]
        if self.rotation == "axis_angle":
            dq = matrix_to_quat(rotvec_to_matrix(dr))
        else:
            dq = dr if self.rotation == "quat_wxyz" else dr[:, [3, 0, 1, 2]]
            dq = dq / np.linalg.norm(dq, axis=1, keepdims=True)
        q = quat_multiply(q0[None], dq)
        q = q * np.where(q[:, :1] < 0, -1.0, 1.0)  # w >= 0 (same rotation)
        return np.concatenate([p0 + a[:, :3] @ r0.T, q, a[:, -1:]], axis=1)


@dataclass(frozen=True)
class PolicyIO:
    """An observation map and an action map (see the module docstring)."""

    name: str = "lerobot"
    observation: ObservationMap = field(default_factory=ObservationMap)
    action: ActionMap = field(default_factory=ActionMap)

    def request(self, obs: dict, prompt: str | None = None) -> dict:
        return self.observation.request(obs, prompt)

    def actions(self, chunk, obs: dict) -> np.ndarray:
        return self.action.actions(chunk, obs)

    def with_n_action_steps(self, n: int | None) -> PolicyIO:
        return self if n is None else replace(self, action=replace(self.action, n_action_steps=int(n)))


_OPENPI_IMAGE = {"layout": "flat", "image_size": (224, 224), "resize": "pad"}
PRESETS: dict[str, PolicyIO] = {
    # LeRobot gym-env keys at the camera's own size; the policy's actions are the env's.
    "lerobot": PolicyIO("lerobot"),
    # openpi LIBERO models (pi0 / pi0-FAST / pi05 _libero): 224x224 padded images, state = end-effector
    # position + axis-angle + finger qpos (8), 7-d per-step actions [dp, d axis-angle, gripper in [-1, 1]]
    # as normalised by LIBERO's OSC controller (x 0.05 m, x 0.5 rad) for an env in relative action mode;
    # 5 actions executed per chunk (openpi's LIBERO example replans every 5 steps).
    "openpi-libero": PolicyIO("openpi-libero", ObservationMap(
        images={"observation/image": "front", "observation/wrist_image": "wrist"},
        state={"observation/state": ("ee_pos", "ee_axis_angle", "gripper_fingers")}, **_OPENPI_IMAGE),
        ActionMap(n_action_steps=5, dims=7, scale=(0.05,) * 3 + (0.5,) * 3 + (1.0,), gripper=(-1.0, 1.0))),
    # openpi DROID models: 224x224 padded exterior + wrist images, 7 joint positions + gripper position;
    # they answer with joint-velocity chunks (10, 8), 8 executed per chunk (openpi's open-loop horizon).
    # twinbench envs observe and command the end effector: this preset needs an env whose observation
    # has `joint_position` and that takes joint-velocity actions.
    "openpi-droid": PolicyIO("openpi-droid", ObservationMap(
        images={"observation/exterior_image_1_left": "front", "observation/wrist_image_left": "wrist"},
        state={"observation/joint_position": ("joint_position",),
               "observation/gripper_position": ("gripper",)},
        **_OPENPI_IMAGE), ActionMap(n_action_steps=8, dims=8)),
    # A policy trained on the reference cell's recordings: end-effector deltas relative to the pose at the
    # chunk's start ([dp, axis-angle, gripper]), executed as absolute targets.
    "chunk-relative": PolicyIO("chunk-relative", ObservationMap(),
                               ActionMap(mode="chunk_relative", rotation="axis_angle")),
}


def _tuples(value):
    return tuple(value) if isinstance(value, list) else value


def policy_io_from_dict(data: dict, name: str = "file") -> PolicyIO:
    """A PolicyIO from a JSON-style dict (module docstring); unknown keys are errors."""
    obs_keys = {"layout", "images", "image_size", "resize", "crop", "flip", "state", "prompt"}
    unknown = sorted(set(data) - obs_keys - {"actions", "preset"})
    if unknown:
        known = sorted(obs_keys | {"actions", "preset"})
        raise ValueError(f"policy io {name}: unknown key(s) {unknown}; known: {known}")
    if "preset" in data and data["preset"] not in PRESETS:
        raise ValueError(f"policy io {name}: unknown preset {data['preset']!r}; presets: {sorted(PRESETS)}")
    base = PRESETS[data["preset"]] if "preset" in data else PolicyIO(name)
    obs_kw = {("prompt_key" if k == "prompt" else k): v for k, v in data.items() if k in obs_keys}
    if "image_size" in obs_kw and obs_kw["image_size"] is not None:
        obs_kw["image_size"] = tuple(int(v) for v in obs_kw["image_size"])
    if "crop" in obs_kw:
        obs_kw["crop"] = {cam: tuple(int(v) for v in box) for cam, box in obs_kw["crop"].items()}
    if "flip" in obs_kw:
        obs_kw["flip"] = tuple(obs_kw["flip"])
    if "state" in obs_kw:
        obs_kw["state"] = {k: tuple(v) for k, v in obs_kw["state"].items()}
    act = dict(data.get("actions") or {})
    act_fields = {f.name for f in fields(ActionMap)}
    bad = sorted(set(act) - act_fields)
    if bad:
        raise ValueError(f"policy io {name}: unknown actions key(s) {bad}; known: {sorted(act_fields)}")
    act = {k: _tuples(v) for k, v in act.items()}
    return PolicyIO(name, replace(base.observation, **obs_kw), replace(base.action, **act))


def load_policy_io(spec: str | PolicyIO | None) -> PolicyIO:
    """A preset name (`lerobot`, `openpi-libero`, `openpi-droid`, `chunk-relative`) or a JSON file."""
    if spec is None or spec == "":
        return PRESETS["lerobot"]
    if isinstance(spec, PolicyIO):
        return spec
    if spec in PRESETS:
        return PRESETS[spec]
    path = Path(spec)
    if not path.is_file():
        raise ValueError(f"policy io {spec!r}: neither a preset ({', '.join(sorted(PRESETS))}) "
                         "nor a JSON file")
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as err:
        raise ValueError(f"policy io file {path}: not valid JSON ({err})") from None
    if not isinstance(data, dict):
        raise ValueError(f"policy io file {path}: expected a JSON object")
    try:
        return policy_io_from_dict(data, name=path.stem)
    except (TypeError, ValueError) as err:
        raise ValueError(f"policy io file {path}: {err}") from None
